"""Light estimation for uncalibrated photometric stereo: LCNet over all images of a capture.

    psctl lights ballPNG     ->  ballPNG/psctl/light_directions.txt, light_intensities.txt, lights.png,
                                 lights_report.json

    >>> from psctl.lights import run_lights
    >>> report = run_lights("ballPNG")            # report["light_mae"] with ground-truth lights

The pipeline (psctl.models.lcnet has the network and the discretisation):

1. Crop and resize. The images are cropped to the mask's bounding box grown by ``margin``
   (15 px, as the authors' ``pmsData_crop``), multiplied by the mask and resized to LCNet's
   input side (128 x 128, bilinear, antialiased); the resized mask is the 4th channel. The
   images are used as captured: light_intensities.txt, if present, is ground truth to compare
   with, never applied (estimating the intensities is LCNet's job).
2. Global feature, pass 1. Images are read one at a time and go through the extractor in chunks;
   the global feature is a running element-wise max of the per-image features [256, 8, 8], so
   memory does not grow with the number of images. Per-image features (64 KB each) are kept up
   to ``cache_mb``.
3. Classification, pass 2. Each image's feature, concatenated with the global one, is
   classified (azimuth, elevation, intensity). Images whose features were not kept are read and
   extracted again (only captures of more than ~1000 images at the default cache).
4. Decoding: the soft-argmax (the default) or the argmax class centre (the paper, ``decode="argmax"``).
5. Symmetric views (``views``, 8 by default; 1 is the paper's single pass): steps 2-4 run on the
   images as captured and turned / mirrored about the view axis (the 8 symmetries of the square,
   ``psctl.symmetry``); each view's directions are turned back and the unit mean
   of the views is the estimate, the intensities their mean. Exact for an orthographic camera
   and isotropic materials; it costs ``views`` times the network work.
6. Refinement (``run_lights(refine=True)``, sdps): a normals network turns the lights into
   normals and ``refine_lights`` refits each light by a robust fit of a diffuse model (a cosine
   that may fall to zero before the terminator) against them, gated by how well that fit
   explains the pixels. Then (``roll``, on by default) the lights are turned about the view axis
   by the roll that makes the normals from them most integrable (``integrability_roll``).

Outputs are in DiLiGenT's format: light_directions.txt (N x 3, unit, x right / y up / z toward
the camera) and light_intensities.txt (N x 3, the same value in R, G and B; only relative
intensities are meaningful). With ground truth in the folder, the report gives the mean angular
error of the directions (``light_mae``, degrees) and the scale-invariant relative intensity
error (``intensity_re``).
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from psctl.arrays import bounding_box
from psctl.errors import ProgressFactory, PsctlError, check_bool, check_path, check_progress, naming
from psctl.hotpixels import clamp_hot_pixels, hot_pixel_notes
from psctl.infer import NO_MASK_NETWORKS_WHY

if TYPE_CHECKING:
    import torch

    from psctl.infer import Reader  # reader(start, box) yields images start.. as float32 [h, w, 3] cropped to box
    from psctl.io.capture import Capture, DecodeMemo
    from psctl.models.lcnet import LCNet
    from psctl.models.weights import Weights

DEFAULT_LIGHTS = {
    "device": "auto",  # auto | cpu | cuda
    "chunk": None,  # images per network batch: None = 8 on CPU, 64 on CUDA
    "margin": 15,  # pixels kept around the mask's bounding box (the authors' DiLiGenT crop)
    "cache_mb": 64,  # per-image features kept from pass 1 for pass 2 (64 KB each at 128 px)
    # a helper process decodes the images (cut to the crop) into a ring of shared memory of at
    # most this many MB while this one imports torch and loads LCNet (psctl.io.prefetch); 0 = off
    "prefetch_mb": 256,
    # soft-argmax: better than the paper's argmax (class centres) on held-out synthetic sets with
    # both release LCNets (7.53 vs 7.67 and 7.60 vs 7.99 degrees; docs/uncalibrated.md)
    "decode": "soft",  # soft | argmax
    # symmetric views averaged (1, 2, 4 or 8 of psctl.symmetry.SYMMETRIES): the images turned
    # and mirrored about the view axis, LCNet's estimates turned back and averaged. 8 was better
    # than 1 on held-out synthetic sets with the release LCNet (docs/uncalibrated.md)
    "views": 8,
    # pad the crop to a square before resizing (False: stretch it to a square, as the authors'
    # code does). Stretching won on the synthetic folder sets (6.41 vs 6.43 degrees over
    # syntest, syntest_dl, syntest_dl_dir; docs/uncalibrated.md)
    "square": False,
    # LCNet answers badly on captures much darker or brighter than its training exposures (mean
    # object radiance 0.02-0.5 times intensities in [0.2, 2]; syntest_dl scaled x0.03 or x3-x30:
    # mean light error 9.5-15 degrees against 4.6 as rendered, session 23). A capture whose mean
    # inside the mask (over all images, as read) is outside this band is scaled to the target for
    # LCNet; every capture measured so far lies inside (DiLiGenT dev split 0.018-0.075, the
    # synthetic test sets 0.014-0.43), so none of their numbers change; scaled syntest_dl with
    # it: 5.89 / 4.90 / 4.78 / 4.78 at x0.03 / 3 / 10 / 30 (docs/uncalibrated.md). None: off.
    "exposure_band": (0.01, 0.5),
    "exposure_target": 0.1,
    # where the guard's mean is taken: "mask" or "lit" (psctl.infer.lit_pixels, the bright part of
    # the frame; what runs without a mask use, so that a dark background does not halve it)
    "exposure_pixels": "mask",
}

OUTPUT_FILES = {"light_directions": "light_directions.txt", "light_intensities": "light_intensities.txt",
                "lights": "lights.png"}
SUBSET_FILE = "light_images.txt"  # with --images: the image each light file row belongs to
# without a mask: the object found for LCNet and the light fit, 0 / 255 as a mask.png, to look at, or
# to copy into the capture folder as mask.png (named mask_*: never read as one of its images)
FOUND_FILE = "mask_found.png"
# the run's report (what --json prints: errors, notes, provenance), beside the light files it
# describes; named as psctl depth's depth_report.json, so never psctl normals' report.json
REPORT_FILE = "lights_report.json"
# psctl normals --method sdps: the lights its normals were estimated from, under names of their own
# so that they never replace psctl lights' files in the same folder (both default to PATH/psctl)
SDPS_FILES = {k: v.replace(".", "_estimated.", 1) for k, v in {**OUTPUT_FILES, "light_images": SUBSET_FILE}.items()}


@dataclass
class LightEstimate:
    directions: np.ndarray  # [N, 3] float32 unit vectors (x right, y up, z toward the camera)
    intensities: np.ndarray  # [N] float32, relative (LCNet's scale, in [0.2, 2.0] unless refined)
    logits: dict[str, np.ndarray]  # {"dir_x": [N, K_d], "dir_y": [N, K_d], "ints": [N, K_e]}, the first view's
    info: dict = field(default_factory=dict)  # device, box, size, chunk, passes, seconds, ...
    notes: list[str] = field(default_factory=list)


# --- the network ------------------------------------------------------------------------------

def load_lcnet(weights: str | os.PathLike | None = None, flag: str = "--weights") -> tuple["LCNet", "Weights"]:
    """LCNet with installed weights (weights/lcnet.pt) or ``weights`` (psctl's file or the
    authors' LCNet_CVPR2019.pth.tar); returns (model, weights). ``flag`` names the option that
    passes a file, for the error message when nothing is installed."""
    from psctl.models.weights import installed_path, load_network, no_weights_error

    check_path(flag.lstrip("-"), weights, optional=True)
    if weights is None and installed_path("lcnet") is None:
        raise no_weights_error("lcnet", flag)
    model, _, w = load_network("lcnet", weights, device="cpu")
    return model, w


def pad_square(x: "torch.Tensor") -> "torch.Tensor":
    """Zero-pad [..., H, W] to [..., S, S], S = max(H, W), centred: resizing then keeps the
    object's aspect ratio (a stretched sphere no longer looks like a sphere to LCNet)."""
    import torch.nn.functional as F

    h, w = x.shape[-2:]
    s = max(h, w)
    return F.pad(x, ((s - w) // 2, s - w - (s - w) // 2, (s - h) // 2, s - h - (s - h) // 2))


def run_lcnet(model: "LCNet", reader: "Reader", n: int, mask: np.ndarray, config: dict | None = None,
              progress: "ProgressFactory | None" = None, label: str = "LCNet") -> LightEstimate:
    """Lights of ``n`` images from a stream, memory bounded in ``n``.

    Args:
        model: an LCNet (eval mode is set here).
        reader: see ``psctl.infer.Reader``; called once, twice when the features do not fit in
            cache_mb, and once more when the exposure guard's inputs do not (info["passes"]).
        n: number of images.
        mask: [H, W] bool object mask (the full image size).
        config: overrides of DEFAULT_LIGHTS.
    Returns:
        LightEstimate with directions [n, 3] and intensities [n].
    """
    import torch

    from psctl.infer import check_float32_scale, exposure_where, lit_mean, pick_device
    from psctl.models.lcnet import FEATURES, decode, resize_inputs
    from psctl.symmetry import SYMMETRIES, check_views, transform_images, untransform_dirs

    cfg = {**DEFAULT_LIGHTS, **(config or {})}
    t0 = time.perf_counter()
    if n < 1:
        raise PsctlError(None, "no images")
    if cfg["decode"] not in ("argmax", "soft"):
        raise PsctlError(None, f"unknown decoding {cfg['decode']!r}; choose argmax or soft")
    where = exposure_where(cfg["exposure_pixels"])
    views = check_views(cfg["views"])
    mask = np.asarray(mask, bool)
    if not mask.any():
        raise PsctlError(None, "mask is empty (no foreground pixel)")
    device = pick_device(cfg["device"])
    model = model.to(device).eval()
    dtype = next(model.parameters()).dtype
    size = int(model.config["size"])
    box = bounding_box(mask, int(cfg["margin"]))
    h, w = box[0].stop - box[0].start, box[1].stop - box[1].start
    crop_mask = mask[box].astype(np.float32)
    chunk = int(cfg["chunk"] or (64 if device.type == "cuda" else 8))
    feat_bytes = FEATURES * (-(-size // 16)) ** 2 * torch.finfo(dtype).bits // 8
    n_cache = max(0, int(cfg["cache_mb"] * 2**20) // (feat_bytes * views))
    # the exposure guard reads every image before pass 1; it keeps the network inputs (4 channels
    # at `size`) for pass 1 when they fit in cache_mb, else pass 1 reads them again
    keep_inputs = n * 4 * size * size * torch.finfo(dtype).bits // 8 <= cfg["cache_mb"] * 2**20
    guard = cfg["exposure_band"] is not None
    passes = int(guard) + int(not (guard and keep_inputs)) + int(n > n_cache)  # reads of the capture
    reads = n * int(guard) + n * int(not (guard and keep_inputs)) + max(0, n - n_cache)
    advance = (progress or (lambda d, t: (lambda k: None)))(label, reads)
    mask_t = torch.from_numpy(crop_mask)[None, None].to(device, dtype)

    peak = [0.0]  # the brightest pixel inside the mask read so far
    hot: dict[int, int] = {}  # image index -> values clamp_hot_pixels set
    level = [0.0, 0.0]  # sum and count of the values inside the mask (the exposure guard's mean)
    # no mask: each pixel's sum, so that the guard's mean is the lit pixels' (infer.lit_pixels),
    # not halved by a dark background (DiLiGenT's ball: 0.018 with its mask, 0.009 without)
    lit_rule = cfg["exposure_pixels"] == "lit" and cfg["exposure_band"] is not None
    pixel_sum = np.zeros((h, w), np.float64) if lit_rule else None

    def chunks(start: int) -> Iterator[torch.Tensor]:
        """Network inputs [c, 4, size, size] of images start.. in chunks."""
        pending: list[np.ndarray] = []
        k = start
        for img in reader(start, box):
            if img.ndim == 2:
                img = img[..., None]
            if img.shape[:2] != (h, w):
                raise PsctlError(None, f"image {k + 1}: size changed while reading")
            img = np.ascontiguousarray(img[..., :3], np.float32)
            if img.shape[-1] == 1:
                img = np.repeat(img, 3, -1)
            if not np.isfinite(img).all():
                raise PsctlError(None, f"image {k + 1} contains NaN or infinite values")
            img, count = clamp_hot_pixels(img * crop_mask[..., None], crop_mask)  # one pixel would move every light
            if count:
                hot[k] = count
            pending.append(img)
            peak[0] = max(peak[0], float(pending[-1].max()))
            level[0] += float(pending[-1].sum(dtype=np.float64))  # inside the mask (zero outside)
            level[1] += 3.0 * float(crop_mask.sum())
            if pixel_sum is not None:
                np.add(pixel_sum, pending[-1].sum(-1, dtype=np.float64), out=pixel_sum)
            advance(1)
            k += 1
            if len(pending) == chunk or k == n:
                x = torch.from_numpy(np.stack(pending)).permute(0, 3, 1, 2).to(device, dtype)
                m = mask_t.expand(len(pending), 1, h, w)
                if cfg["square"]:
                    x, m = pad_square(x), pad_square(m)
                x, m = resize_inputs(x, m, size)
                yield model.network_input(x, m)
                pending = []
        if k != n or pending:
            raise PsctlError(None, f"expected {n} images, got {k}")

    # exposure: the mean inside the mask over all images, as read (full resolution), before any
    # feature; the network inputs are kept for pass 1 when they fit in cache_mb, else read again
    factor, buffered, mean = 1.0, None, None
    band = cfg["exposure_band"]
    if band is not None:
        buffered = []
        with torch.inference_mode():
            for x in chunks(0):
                if keep_inputs:
                    buffered.append(x)
        buffered = buffered if keep_inputs else None
        mean = level[0] / max(level[1], 1.0)
        if pixel_sum is not None and mean > 0:
            mean = lit_mean(pixel_sum, n)
        pixel_sum = None  # the closure's too: later passes neither add to it nor keep it
        if mean > 0 and not band[0] <= mean <= band[1]:
            factor = check_float32_scale(float(cfg["exposure_target"]) / mean, mean, where)

    def scaled(xs: Iterator[torch.Tensor]) -> Iterator[torch.Tensor]:
        for x in xs:
            if factor != 1.0:
                x = torch.cat([x[:, :3] * factor, x[:, 3:]], 1)
            yield x

    fuse_max = model.config["fuse"] == "max"
    syms = SYMMETRIES[:views]
    with torch.inference_mode():
        fused: list[torch.Tensor | None] = [None] * views
        cache: list[list[torch.Tensor]] = [[] for _ in syms]
        kept = 0
        # pass 1: the global features (and the first features), one per view
        for x in scaled(buffered if buffered is not None else chunks(0)):
            take = min(len(x), n_cache - kept)
            for v, sym in enumerate(syms):
                f = model.extract(transform_images(x, sym))
                fm = f.amax(0, keepdim=True) if fuse_max else f.sum(0, keepdim=True)
                fused[v] = fm if fused[v] is None else (torch.maximum(fused[v], fm) if fuse_max else fused[v] + fm)
                if take > 0:
                    cache[v].append(f[:take].clone())
            kept += max(take, 0)
        if not peak[0] > 0:  # LCNet would still answer, with lights that mean nothing
            raise PsctlError(None, "all images are black inside the mask")
        if not fuse_max:
            fused = [f / n for f in fused]
        logits: list[dict[str, list[torch.Tensor]]] = [{"dir_x": [], "dir_y": [], "ints": []} for _ in syms]

        def classify(v: int, f: torch.Tensor) -> None:
            for i in range(0, len(f), chunk):
                out = model.classify(f[i:i + chunk], fused[v])
                for key in logits[v]:
                    logits[v][key].append(out[key].float().cpu())

        for v in range(views):  # pass 2: classify each image against its view's global feature
            for f in cache[v]:
                classify(v, f)
        cache.clear()
        buffered = None  # pass 1 is done with them
        if kept < n:
            for x in scaled(chunks(kept)):
                for v, sym in enumerate(syms):
                    classify(v, model.extract(transform_images(x, sym)))
    outs = [{k: torch.cat(val) for k, val in lv.items()} for lv in logits]
    decoded = [decode(o, model.config, cfg["decode"]) for o in outs]
    dirs = torch.nn.functional.normalize(torch.stack([untransform_dirs(d, sym) for (d, _), sym in zip(decoded, syms)]).mean(0),
                                         dim=-1)
    ints = torch.stack([i for _, i in decoded]).mean(0)
    out = outs[0]
    info = {"device": str(device), "box": [box[0].start, box[0].stop, box[1].start, box[1].stop],
            "size": size, "chunk": chunk, "passes": passes, "cached_features": kept, "decode": cfg["decode"], "views": views,
            "exposure": round(factor, 6), "seconds": round(time.perf_counter() - t0, 3)}
    if hot:
        info["hot_pixels"] = dict(sorted(hot.items()))
    notes = []
    if factor != 1.0:
        notes.append(f"lcnet: the images' mean {where}, {mean:.3g}, is outside the exposures LCNet was "
                     f"trained on ({band[0]:g} to {band[1]:g}); it sees them scaled by {factor:.3g}")
    notes += [note for note in [few_lights_note(n)] if note]
    return LightEstimate(dirs.numpy().astype(np.float32), ints.numpy().astype(np.float32),
                         {k: v.numpy() for k, v in out.items()}, info, notes)


# LCNet compares a capture's images with one another (its global feature is a max over them) and
# learnt on 32 at a time: from few it is rougher. The DiLiGenT dev split, 6 random subsets of each
# object's images (estimate_lights' defaults, session 69): 14.97 degrees off on average from 1
# image, 9.69 from 2, 6.30 from 4, 4.87 from 8, 2.91 from all 96.
FEW_LIGHT_IMAGES = 8


def few_lights_note(n: int) -> str | None:
    """The note for LCNet given fewer than FEW_LIGHT_IMAGES images, else None."""
    if n >= FEW_LIGHT_IMAGES:
        return None
    return (f"lights: only {n} image{'s' * (n != 1)}: LCNet estimates each light by comparing the images with one "
            f"another, and from few it is rougher (the DiLiGenT dev split's objects, random subsets: 15.0 degrees "
            f"off on average from 1 image, 9.7 from 2, 6.3 from 4, 4.9 from 8, 2.9 from all 96)")


def array_lights(images: np.ndarray, mask: np.ndarray | None = None, weights: str | os.PathLike | None = None,
                 config: dict | None = None, model: "LCNet | None" = None,
                 progress: "ProgressFactory | None" = None) -> LightEstimate:
    """Lights from in-memory images [N, H, W, 3] (or [N, H, W]), as captured (not divided by any
    intensity). ``model`` (an LCNet) replaces loading ``weights`` / the installed weights."""
    from psctl.arrays import as_images, as_mask, check_not_black

    images = as_images(images)  # integer arrays scaled as image files are; grey / RGBA to RGB
    n, H, W = images.shape[:3]
    mask = as_mask(mask, (H, W))
    check_not_black(images, mask)
    if mask is None:  # the whole frame; the exposure guard reads its lit part
        mask, config = np.ones((H, W), bool), {"exposure_pixels": "lit", **(config or {})}
    note = None
    if model is None:
        model, w = load_lcnet(weights)
        note = f"lcnet: weights {w.path}" + (" (the authors' checkpoint)" if w.official else "")
        if w.official:  # the guard's band describes psctl's training exposures, not the authors'
            config = {"exposure_band": None, **(config or {})}

    def reader(start: int, box: tuple[slice, slice]) -> Iterator[np.ndarray]:
        for k in range(start, n):
            yield images[k][box]

    res = run_lcnet(model, reader, n, mask, config, progress)
    if note:
        res.notes.append(note)
    res.notes += hot_pixel_notes(res.info, [f"image {k + 1}" for k in range(n)])
    return res


def capture_lights(capture: "Capture", mask: np.ndarray, weights: str | os.PathLike | None = None,
                   config: dict | None = None, progress: "ProgressFactory | None" = None,
                   flag: str = "--weights", memo: "DecodeMemo | None" = None,
                   keep_box: tuple[slice, slice] | None = None) -> LightEstimate:
    """Lights of a capture folder, streaming its images from disk as captured (the folder's
    light_intensities.txt, if any, is not applied). ``memo`` (``DecodeMemo``): the decoded
    images are kept there for a later pass (sdps' second stage); ``keep_box``: what that pass
    reads of each image (``psctl.infer.first_read_box``), decoded here with LCNet's crop so that
    the memo serves it."""
    from psctl.io.capture import ImageCheck
    from psctl.io.prefetch import prefetch

    if capture.mask_path is None:  # the exposure guard reads the lit pixels
        config = {"exposure_pixels": "lit", **(config or {})}
    cfg = {**DEFAULT_LIGHTS, **(config or {})}
    mask = np.asarray(mask, bool)
    on = mask.any() and mask.shape == (capture.height, capture.width)
    box = bounding_box(mask, int(cfg["margin"])) if on else None
    # decoded once for both passes: the smallest box holding LCNet's crop and the later pass's
    read = box if box is None or keep_box is None or memo is None else (
        slice(min(box[0].start, keep_box[0].start), max(box[0].stop, keep_box[0].stop)),
        slice(min(box[1].start, keep_box[1].start), max(box[1].stop, keep_box[1].stop)))
    # started before LCNet's weights import torch: the decoding overlaps that import
    with prefetch(capture.image_paths, read, (capture.width, capture.height), cfg["prefetch_mb"]) as pf:
        model, w = load_lcnet(weights, flag)
        if w.official:  # the guard's band describes psctl's training exposures, not the authors'
            config = {"exposure_band": None, **(config or {})}
        raw = replace(capture, intensities=np.ones_like(capture.intensities))
        check = ImageCheck(capture)  # black images, negative values: notes
        reader = check.reader(raw, mask, pf, memo)
        if read != box:
            reader = _cut_reader(reader, check.reader(raw, mask, pf, memo, _inner(box, read)), box, read)
        with naming(capture.path):  # all images black, ...
            res = run_lcnet(model, reader, raw.n_images, mask, config, progress, f"{capture.name}: reading + LCNet")
        res.info["prefetched"] = pf.served
    res.notes.append(f"lcnet: weights {w.path}" + (" (the authors' checkpoint)" if w.official else ""))
    res.notes += check.notes() + hot_pixel_notes(res.info, [p.name for p in capture.image_paths])
    return res


def _inner(box: tuple[slice, slice], outer: tuple[slice, slice]) -> tuple[slice, slice]:
    """``box`` (inside ``outer``) in the coordinates of an array cut to ``outer``."""
    return tuple(slice(b.start - o.start, b.stop - o.start) for o, b in zip(outer, box))


def _cut_reader(reader: "Reader", outer_reader: "Reader", box: tuple[slice, slice],
                outer: tuple[slice, slice]) -> "Reader":
    """A reader that, asked for ``box``, has ``outer_reader`` read ``outer`` (which holds
    ``box``; the images a later pass reads) and cuts each image to ``box``; any other box it
    leaves to ``reader``. ``outer_reader`` runs its checks on ``box``'s part, as ``reader``
    would on ``box``: the object's pixels for the notes, and the ambient image's check."""
    cut = _inner(box, outer)

    def read(start: int, asked: tuple[slice, slice]) -> Iterator[np.ndarray]:
        if asked != box:
            yield from reader(start, asked)
            return
        for img in outer_reader(start, outer):
            yield np.ascontiguousarray(img[cut])

    return read


# --- refinement against the normals (sdps) ---------------------------------------------------

# Why: LCNet classifies each image's light from a 128 x 128 view; once a network has estimated
# the normals from those lights, the full-resolution pixels pin each light down better wherever
# the surface is mostly diffuse. Chosen on synthetic folders (docs/uncalibrated.md, "Light
# refinement"); the gate keeps LCNet's lights where a diffuse model explains the pixels badly
# (metals, deep concavities).
_REFINE_BLOCK = 2048  # pixels per block of refine_lights' [pixels, images] arrays
FALLOFFS = ("shifted", "lambertian")  # refine_lights' shading models (DEFAULT_REFINE["falloff"])
DEFAULT_REFINE = {
    "pixels": 20000,  # mask pixels sampled for the fit (seeded): enough to fix 3 numbers per light
    "iters": 5,  # alternations of per-pixel albedo and per-image light
    "margin": 0.1,  # a light lights a pixel when n.s > margin |s|: keeps the terminator out of the fit
    # per image, only pixels whose observed / predicted ratio lies within these quantiles: cast
    # shadows and interreflections (low) and highlights (high) out
    "trim": (0.1, 0.9),
    # the fit's relative residual q (median |o - rho (n.s + b)| / median o over lit observations,
    # n.s + b > 0 too): at or below gate[0] the fitted lights are used, at or above gate[1]
    # LCNet's are kept, blended between. gate[1] was 0.10 for the Lambertian fit (sessions 16-19);
    # 0.15 since session 20, chosen with the shifted falloff on synthetic folders
    # (docs/uncalibrated.md, "Falloff")
    "gate": (0.05, 0.15),
    # a fitted light further than this from its start (degrees) means the fit went astray (on a
    # mirror-like surface it can shrink the lit set until a few pixels fit): the start is kept.
    # There is no horizon check: a fitted light may end slightly below it (z < 0) and is then
    # written and used as it is
    "max_change": 30.0,
    # the shading model: "shifted", o = rho (n.s + b) with b <= 0 per image, a cosine that falls
    # to zero before the terminator; or "lambertian", o = rho max(n.s, 0) (b = 0; the default until
    # session 20). Cast shadows and many real reflectances fall off faster than a cosine near the
    # terminator, which pulls a Lambertian fit's lights outward (docs/uncalibrated.md, "Falloff");
    # b > 0 (a flatter falloff: glossy surfaces) is refused because there the extra freedom lets
    # the fit run away
    "falloff": "shifted",
    "seed": 0,
    # after the fit, turn the lights and the final normals about the view axis by the roll that
    # makes those normals most integrable (``integrability_roll``): the one part of a rotation
    # shared by lights and normals that the fit cannot see and integrability can
    # (docs/uncalibrated.md, "Roll from integrability"; on since session 22: lower normal and light
    # errors on all four synthetic decision sets)
    "roll": True,
    "roll_erode": 3,  # mask pixels this close to the edge left out (rims and silhouettes are unreliable)
    "max_roll": 15.0,  # a larger roll (degrees) is refused and the lights kept: not a small correction
}


@dataclass
class Refinement:
    directions: np.ndarray  # [N, 3] unit
    intensities: np.ndarray  # [N], on the scale of the intensities passed in (their geometric mean)
    quality: float  # q, the fit's relative residual (inf when nothing was fitted)
    weight: float  # in [0, 1]: 1 = the fitted lights, 0 = the ones passed in
    status: str = "fitted"  # fitted | too few pixels | astray (see DEFAULT_REFINE["max_change"]) | undetermined


def refine_lights(observations: np.ndarray, normals: np.ndarray, directions: np.ndarray,
                  intensities: np.ndarray, config: dict | None = None) -> Refinement:
    """Refine lights by a robust Lambertian (or shifted-cosine) fit against known normals.

    Model: o[j, p] = rho[p] * max(n[p] . s[j] + b[j], 0) with s[j] = |s[j]| l[j]; b = 0 for the
    "lambertian" falloff, b[j] <= 0 fitted per image for "shifted" (then e[j] = |s[j]| + b[j], the
    brightness where n = l). Starting from the given lights, alternate rho (least squares per
    pixel over the observations it is lit in) and s[j], b[j] (least squares per image over lit
    pixels, trimmed by ``trim``). The fit's residual q decides, through ``gate``, how much of it
    replaces the lights passed in.

    Args:
        observations: [N, P] grey values as captured (not divided by any intensity); NaN where
            one is not to be used (saturated).
        normals: [P, 3] unit normals of the same pixels (e.g. PS-FCN's from the lights below).
        directions: [N, 3] unit light directions to start from (LCNet's).
        intensities: [N] their intensities.
        config: overrides of DEFAULT_REFINE.
    Returns:
        Refinement (directions [N, 3], intensities [N], quality q, weight, status).
    """
    cfg = {**DEFAULT_REFINE, **(config or {})}
    # observations stay float32 (as sampled) and [P, N] arrays are only made a block of pixels at a
    # time: whole, in float64, they were about 0.5 GB for 960 images (session 38)
    o = np.asarray(observations, np.float32)
    n = np.asarray(normals, np.float64)
    d0 = np.asarray(directions, np.float64)
    e0 = np.asarray(intensities, np.float64).reshape(-1)
    if o.ndim != 2 or n.shape != (o.shape[1], 3) or d0.shape != (o.shape[0], 3) or e0.shape != (o.shape[0],):
        raise ValueError(f"shapes: observations {o.shape}, normals {n.shape}, directions {d0.shape}, "
                         f"intensities {e0.shape}")
    if cfg["falloff"] not in FALLOFFS:
        raise ValueError(f"falloff must be one of {FALLOFFS}, not {cfg['falloff']!r}")
    keep = Refinement(d0.astype(np.float32), e0.astype(np.float32), float("inf"), 0.0, "too few pixels")
    # NaN: an observation not to use (a saturated one: its true value is unknown, and taking the top
    # code for it pulls the light toward the clipped highlight); a pixel keeps its other observations
    seen = np.isfinite(o)
    ok = seen.any(0) & np.isfinite(n).all(1) & (np.linalg.norm(n, axis=1) > 0.5)
    if not ok.all():
        o, n, seen = o[:, ok], n[ok], seen[:, ok]
    gaps = not seen.all()
    if gaps:
        o = np.where(seen, o, np.float32(0.0))
    if n.shape[0] < 50 or not (np.all(e0 > 0) and np.isfinite(d0).all()):
        return keep
    from psctl.classic import lights_problem

    if lights_problem(d0) is not None:  # fewer than 3 lights, or coplanar: any light fits (residual 0)
        return replace(keep, status="undetermined")
    shifted = cfg["falloff"] == "shifted"
    lo_q, hi_q = cfg["trim"]
    s = d0 * e0[:, None]
    b = np.zeros(len(s))
    blocks = [slice(a, a + _REFINE_BLOCK) for a in range(0, len(n), _REFINE_BLOCK)]

    def shading(px: slice, s: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Shading n.s + b [p, N] of a block of pixels, and where each light lights them."""
        sh = n[px] @ s.T
        lit = sh > cfg["margin"] * np.linalg.norm(s, axis=1)[None]
        sh += b[None]
        lit &= sh > 0
        if gaps:
            lit &= seen[:, px].T  # an observation left out counts as not lit: in no sum below
        return sh, lit

    def albedo(s: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """lit [P, N] and the least-squares albedo rho [P] over each pixel's lit observations."""
        lit, rho = np.empty((len(n), len(s)), bool), np.empty(len(n))
        for px in blocks:
            sh, lit[px] = shading(px, s, b)
            shl = sh * lit[px]
            den = (shl ** 2).sum(1)
            rho[px] = np.where(den > 0, (o[:, px].T * shl).sum(1) / np.maximum(den, 1e-300), 0.0)
        return lit, rho

    for _ in range(int(cfg["iters"])):
        lit, rho = albedo(s, b)
        new, new_b = s.copy(), b.copy()
        for j in range(len(s)):
            use = np.flatnonzero(lit[:, j] & (rho > 0))
            if use.size < 10:
                continue  # (nearly) no lit pixel for this light: keep it
            ratio = o[j, use] / (rho[use] * (n[use] @ s[j] + b[j]))
            lo, hi = np.quantile(ratio, (lo_q, hi_q))
            use = use[(ratio >= lo) & (ratio <= hi)]
            if use.size < 10:
                continue
            a = rho[use, None] * n[use]
            oj = o[j, use].astype(np.float64)
            sol4 = np.linalg.lstsq(np.concatenate([a, rho[use, None]], 1), oj, rcond=None)[0] if shifted else None
            if sol4 is not None and sol4[3] < 0 and np.linalg.norm(sol4[:3]) + sol4[3] > 0:
                sol, off = sol4[:3], sol4[3]
            else:  # b = 0: the Lambertian fit
                sol, off = np.linalg.lstsq(a, oj, rcond=None)[0], 0.0
            if np.isfinite(sol).all() and np.isfinite(off) and np.linalg.norm(sol) > 0:
                new[j], new_b[j] = sol, off
        k = np.linalg.norm(new, axis=1).mean()  # the fit fixes rho * e only up to one scale
        s, b = new / k, new_b / k
    if not (np.isfinite(s).all() and np.isfinite(b).all()):
        return keep
    fitted = s / np.linalg.norm(s, axis=1, keepdims=True)
    change = np.degrees(np.arccos(np.clip((fitted * d0).sum(1), -1, 1)))
    if (change > cfg["max_change"]).any():
        return replace(keep, status="astray")
    lit, rho = albedo(s, b)
    if not lit.any():
        return keep
    lit_obs = np.empty(int(lit.sum()))  # one buffer: the residuals' median, then the observations'
    medians = []
    for residual in (True, False):
        at = 0
        for px in blocks:
            sh, li = shading(px, s, b)
            v = o[:, px].T[li].astype(np.float64)
            lit_obs[at:at + v.size] = np.abs(v - (rho[px, None] * sh)[li]) if residual else v
            at += v.size
        medians.append(float(np.median(lit_obs, overwrite_input=True)))
    q = medians[0] / max(medians[1], 1e-12)
    lo_g, hi_g = cfg["gate"]
    w = float(np.clip((hi_g - q) / (hi_g - lo_g), 0.0, 1.0)) if np.isfinite(q) else 0.0
    e = np.linalg.norm(s, axis=1) + b  # the brightness of a pixel facing the light (b = 0: |s|)
    d = w * fitted + (1 - w) * d0
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    # intensities blended in log space, each set first divided by its geometric mean; the result
    # is given the geometric mean of the intensities passed in
    g0 = np.exp(np.log(e0).mean())
    e = g0 * np.exp(w * (np.log(e) - np.log(e).mean()) + (1 - w) * (np.log(e0) - np.log(g0)))
    return Refinement(d.astype(np.float32), e.astype(np.float32), q, w)


def sample_observations(reader: "Reader", n: int, mask: np.ndarray, normals: np.ndarray,
                        config: dict | None = None,
                        advance: Callable[[int], None] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Grey observations [n, P] and normals [P, 3] at up to ``pixels`` seeded mask pixels.

    ``reader(start, box)`` yields the images as captured (see ``psctl.infer.Reader``); they are
    read once, and only the sampled pixels are kept (P values per image)."""
    cfg = {**DEFAULT_REFINE, **(config or {})}
    mask = np.asarray(mask, bool) & (np.linalg.norm(normals, axis=-1) > 0.5)
    if not mask.any():
        return np.zeros((n, 0), np.float32), np.zeros((0, 3), np.float32)
    box = bounding_box(mask)
    ys, xs = np.nonzero(mask[box])
    if ys.size > cfg["pixels"]:
        pick = np.sort(np.random.default_rng(cfg["seed"]).choice(ys.size, int(cfg["pixels"]), replace=False))
        ys, xs = ys[pick], xs[pick]
    obs = np.empty((n, ys.size), np.float32)
    k = 0
    for img in reader(0, box):
        if k >= n:
            break
        img = np.asarray(img, np.float32)
        obs[k] = img[ys, xs].mean(-1) if img.ndim == 3 else img[ys, xs]
        k += 1
        if advance is not None:
            advance(1)
    if k != n:
        raise PsctlError(None, f"expected {n} images, got {k}")
    return obs, np.asarray(normals, np.float32)[box][ys, xs]


def refine_estimate(est: LightEstimate, reader: "Reader", n: int, mask: np.ndarray, normals: np.ndarray,
                    config: dict | None = None, method: str = "PS-FCN", progress: "ProgressFactory | None" = None,
                    label: str = "reading for the light fit") -> LightEstimate:
    """``est`` with its lights refined against ``normals`` [H, W, 3] (``refine_lights``); the
    capture is read once more. ``info["refine"]`` and a note say what happened."""
    t0 = time.perf_counter()
    advance = progress(label, n) if progress is not None else None
    obs, nrm = sample_observations(reader, n, mask, normals, config, advance)
    ref = refine_lights(obs, nrm, est.directions, est.intensities, config)
    cfg = {**DEFAULT_REFINE, **(config or {})}
    info = {**est.info, "refine": {"quality": None if not np.isfinite(ref.quality) else round(ref.quality, 4),
                                   "weight": round(ref.weight, 3), "status": ref.status, "pixels": int(obs.shape[1]),
                                   "gate": list(cfg["gate"]), "falloff": cfg["falloff"],
                                   "seconds": round(time.perf_counter() - t0, 3)}}
    if ref.status == "astray":
        note = (f"lights: LCNet's lights kept (refitting them against {method}'s normals moved a light by more than "
                f"{cfg['max_change']:g} degrees)")
    elif ref.status == "undetermined":
        note = (f"lights: LCNet's lights kept ({len(est.directions)} image(s) with (nearly) coplanar estimated "
                f"lights: a fit against {method}'s normals would be undetermined)" if len(est.directions) >= 3 else
                f"lights: LCNet's lights kept (only {len(est.directions)} image(s): a fit against {method}'s normals "
                f"would be undetermined)")
    elif not np.isfinite(ref.quality):
        note = "lights: too few usable pixels to refine LCNet's lights against the normals; LCNet's kept"
    elif ref.weight >= 1:
        note = f"lights: LCNet's lights refined against {method}'s normals (fit residual {ref.quality:.3g})"
    elif ref.weight <= 0:
        note = (f"lights: LCNet's lights kept (a diffuse fit against {method}'s normals explains this object "
                f"poorly: residual {ref.quality:.3g} >= {cfg['gate'][1]})")
    else:
        note = (f"lights: LCNet's lights {info['refine']['weight']:.0%} refined against {method}'s normals (fit "
                f"residual {ref.quality:.3g})")
    return replace(est, directions=ref.directions, intensities=ref.intensities, info=info, notes=[*est.notes, note])


def integrability_roll(normals: np.ndarray, mask: np.ndarray | None = None, erode: int = 3) -> tuple[float, float, int]:
    """The turn about the view axis that makes a normal map most integrable.

    A surface's gradient field (dz/dcol, dz/drow) = (-nx/nz, +ny/nz) has no curl; scaled by
    nz^2 (bounded where the surface is steep) the curl is, per pixel and its right and lower
    neighbours (forward differences),
    r = -nz dnx/drow + nx dnz/drow - nz dny/dcol + ny dnz/dcol. Turning the normals by an angle t
    about the view axis leaves nz and turns (nx, ny), so r(t) = cos(t) r(0) + sin(t) r(90 deg) and
    the t minimising the sum of r(t)^2 has a closed form. Turns about in-plane axes change r far
    less (docs/uncalibrated.md, "Roll from integrability"), so only the roll is estimated.

    Args:
        normals: [H, W, 3] normals, x right / y up / z toward the camera.
        mask: [H, W] bool (None: the pixels with a nonzero normal).
        erode: pixels this close to the mask's edge are left out.
    Returns:
        (roll in degrees, counterclockwise seen from the camera: turning the normals by it makes
        them most integrable; the residual's relative drop sum r(0)^2 / sum r(roll)^2 >= 1; the
        number of pixels used, each with both neighbours inside). (0, 1, k) when fewer than 100
        are usable.
    """
    terms, k = _curl_terms(normals, mask, erode)
    if k < 100:
        return 0.0, 1.0, k
    aa, ab, bb = terms[0]
    t = 0.5 * np.arctan2(-2.0 * ab, bb - aa)  # where E(t) below is smallest
    e = _smallest_residual(aa, ab, bb)
    return float(np.degrees(t)), float(aa / e) if e > 0 else 1.0, k


def _smallest_residual(aa: float, ab: float, bb: float) -> float:
    """min over t of E(t) = (aa + bb)/2 + (aa - bb)/2 cos 2t + ab sin 2t, the curl residual of
    the normals turned by t (the minimum is where (cos 2t, sin 2t) points against ((aa - bb)/2, ab))."""
    return (aa + bb) / 2 - float(np.sqrt(((aa - bb) / 2) ** 2 + ab ** 2))


def erode_mask(mask: np.ndarray, iterations: int) -> np.ndarray:
    """[H, W] bool eroded ``iterations`` times by the 4-neighbour cross, outside the image counting
    as background: scipy.ndimage.binary_erosion's default, in numpy (importing scipy.ndimage took
    0.17 s of every calibrated run, which checks the normals' integrability with it)."""
    ok = np.asarray(mask, bool)
    for _ in range(iterations):
        e = ok.copy()
        e[1:] &= ok[:-1]
        e[:-1] &= ok[1:]
        e[:, 1:] &= ok[:, :-1]
        e[:, :-1] &= ok[:, 1:]
        e[[0, -1]] = False
        e[:, [0, -1]] = False
        ok = e
    return ok


def _curl_terms(normals: np.ndarray, mask: np.ndarray | None, erode: int,
                mirrors: tuple[bool, ...] = (False,)) -> tuple[list[tuple[float, float, float]], int]:
    """([(aa, ab, bb) per entry of ``mirrors``], k): the sums r0.r0, r0.r90, r90.r90 of
    integrability_roll's curl residual r0 of the normals (x negated for a True entry) and r90 of
    the same turned by 90 degrees, over the k usable pixels (no sums when k < 100)."""
    n = np.asarray(normals, np.float64)
    ok = np.isfinite(n).all(-1)
    n = np.where(ok[..., None], n, 0.0)
    ok &= np.linalg.norm(n, axis=-1) > 0.5
    if mask is not None:
        ok &= np.asarray(mask, bool)
    if erode > 0:
        ok = erode_mask(ok, int(erode))
    block = ok[:-1, :-1] & ok[1:, :-1] & ok[:-1, 1:]
    k = int(block.sum())
    if k < 100:
        return [], k

    def curl(nx: np.ndarray, ny: np.ndarray, nz: np.ndarray) -> np.ndarray:
        def drow(a: np.ndarray) -> np.ndarray:  # forward differences down the rows
            return a[1:, :-1] - a[:-1, :-1]

        def dcol(a: np.ndarray) -> np.ndarray:  # and along the columns
            return a[:-1, 1:] - a[:-1, :-1]

        x, y, z = nx[:-1, :-1], ny[:-1, :-1], nz[:-1, :-1]
        return (-z * drow(nx) + x * drow(nz) - z * dcol(ny) + y * dcol(nz))[block]

    sums = []
    for mirror in mirrors:
        nx, ny, nz = (-1.0 if mirror else 1.0) * n[..., 0], n[..., 1], n[..., 2]
        a0, a90 = curl(nx, ny, nz), curl(-ny, nx, nz)  # turned by 90 degrees: (nx, ny) -> (-ny, nx)
        sums.append((float(a0 @ a0), float(a0 @ a90), float(a90 @ a90)))
    return sums, k


def mirror_ratio(normals: np.ndarray, mask: np.ndarray | None = None, erode: int = 3) -> float | None:
    """How much less integrable a normal map is than its mirror image: the smallest curl residual
    over turns about the view axis (integrability_roll) of the normals with x negated, over that
    of the normals as they are. Below 1 the mirrored field is the more integrable one, which is
    what a light file with one axis flipped (y down, as image rows) gives: L2 then returns exactly
    the mirrored normals, and the networks nearly. x and y flips cannot be told apart (they
    differ by a half turn). None when fewer than 100 pixels are usable."""
    terms, k = _curl_terms(normals, mask, erode, mirrors=(False, True))
    if k < 100:
        return None
    e0, e1 = (_smallest_residual(*t) for t in terms)
    return float(e1 / e0) if e0 > 0 else None


def turn_about_view_axis(vectors: np.ndarray, degrees: float) -> np.ndarray:
    """[..., 3] vectors turned counterclockwise (seen from the camera) about the z axis."""
    t = np.radians(degrees)
    c, s = np.cos(t), np.sin(t)
    v = np.asarray(vectors)
    out = v.copy()
    out[..., 0] = c * v[..., 0] - s * v[..., 1]
    out[..., 1] = s * v[..., 0] + c * v[..., 1]
    return out


def lights_changed(info: dict | None) -> bool:
    """Whether a refinement report (``info["refine"]``) says LCNet's lights were changed: fitted
    with some weight, or turned by the roll."""
    return bool(info) and (info["weight"] > 0 or (info.get("roll") or {}).get("status") == "applied")


def wants_roll(config: dict | None = None) -> bool:
    """Whether the refinement ``config`` (over DEFAULT_REFINE) turns the lights by the normals' roll."""
    return bool({**DEFAULT_REFINE, **(config or {})}["roll"])


def roll_estimate(est: LightEstimate, normals: np.ndarray, mask: np.ndarray | None,
                  config: dict | None = None) -> tuple[LightEstimate, np.ndarray]:
    """``est`` and the normals it gave [H, W, 3], both turned about the view axis by the normals'
    ``integrability_roll`` when ``config`` (over DEFAULT_REFINE) has "roll" on; unchanged
    otherwise. ``info["refine"]["roll"]`` and a note say what happened."""
    cfg = {**DEFAULT_REFINE, **(config or {})}
    if not cfg["roll"]:
        return est, normals
    t, gain, k = integrability_roll(normals, mask, cfg["roll_erode"])
    if k < 100:
        status, note = "too few pixels", "lights: too few pixels to read the normals' roll; not turned"
    elif abs(t) > cfg["max_roll"]:
        status, note = "refused", (f"lights: not turned about the view axis (the normals' roll, {t:+.1f} degrees, "
                                   f"is beyond {cfg['max_roll']:g})")
    else:
        status, note = "applied", (f"lights: turned {t:+.1f} degrees about the view axis, the roll that makes the "
                                   "normals from them most integrable")
    info = {**est.info, "refine": {**(est.info.get("refine") or {}),
                                   "roll": {"degrees": round(t, 3), "gain": round(gain, 5), "status": status}}}
    if status == "applied" and abs(t) < 0.05:  # "+0.0 degrees" says nothing; the report keeps the value
        note = None
    est = replace(est, info=info, notes=[*est.notes, *([note] if note else [])])
    if status != "applied":
        return est, normals
    est = replace(est, directions=turn_about_view_axis(est.directions, t).astype(np.float32))
    return est, turn_about_view_axis(normals, t).astype(np.float32)


def refine_config(falloff: str | None, roll: bool | None = None) -> dict | None:
    """The refinement's config for a user's ``--falloff`` and ``--roll/--no-roll`` (None:
    DEFAULT_REFINE's); one-line error for a falloff other than "shifted" or "lambertian"."""
    if isinstance(falloff, str):
        falloff = falloff.lower()  # as --method: Lambertian is lambertian
    if falloff is not None and falloff not in FALLOFFS:
        raise PsctlError(None, f"--falloff must be {' or '.join(FALLOFFS)}, not {falloff!r}")
    if roll is not None and not isinstance(roll, (bool, np.bool_)):
        raise PsctlError(None, f"roll must be True, False or None, not {roll!r}")
    cfg = {k: v for k, v in (("falloff", falloff), ("roll", roll)) if v is not None}
    return cfg or None


def lit_capture(capture: "Capture", est: LightEstimate) -> "Capture":
    """``capture`` with ``est``'s lights in place of its light files (the same intensity in R, G
    and B): what sdps' second stage reads (intensities_given False: the folder's file is not them)."""
    return replace(capture, lights=est.directions, intensities=np.repeat(est.intensities[:, None], 3, 1),
                   intensities_given=False)


def refine_capture(capture: "Capture", mask: np.ndarray, est: LightEstimate, normals: np.ndarray,
                   method: str = "PS-FCN", progress: "ProgressFactory | None" = None,
                   config: dict | None = None, memo: "DecodeMemo | None" = None) -> LightEstimate:
    """``refine_estimate`` on a capture folder's images as captured (its light_intensities.txt,
    if any, is not applied: the fit estimates the intensities). ``memo``: as ``iter_images``."""
    from psctl.io.capture import iter_images

    # the estimate's directions: near lights' falloff follows them (psctl.nearlight)
    raw = replace(capture, lights=est.directions, intensities=np.ones_like(capture.intensities))

    def reader(start: int, box: tuple[slice, slice]) -> Iterator[np.ndarray]:
        top: dict[int, np.ndarray] = {}  # each integer image's pixels at its top code (saturated)
        for k, img in enumerate(iter_images(raw.subset(range(start, raw.n_images)), box, memo=memo,
                                            clipped=top.__setitem__)):
            sat = top.pop(k, None)
            if sat is not None and sat.any():  # left out of the fit (refine_lights: NaN)
                img = img.copy()
                img[sat] = np.nan
            yield img

    return refine_estimate(est, reader, capture.n_images, mask, normals, config, method=method, progress=progress,
                           label=f"{capture.name}: reading for the light fit")


def refine_arrays(images: np.ndarray, mask: np.ndarray | None, est: LightEstimate, normals: np.ndarray,
                  method: str = "PS-FCN", config: dict | None = None,
                  saturated: np.ndarray | None = None) -> LightEstimate:
    """``refine_estimate`` on in-memory images [N, H, W, 3] as captured; ``saturated`` [N, H, W]
    bool, the observations to leave out (as ``refine_capture`` leaves out a file's top code)."""
    m = np.ones(images.shape[1:3], bool) if mask is None else np.asarray(mask, bool)

    def reader(start: int, box: tuple[slice, slice]) -> Iterator[np.ndarray]:
        for k in range(start, len(images)):
            img = images[k][box]
            if saturated is not None and saturated[k][box].any():
                img = np.where(saturated[k][box][..., None], np.float32(np.nan), img).astype(np.float32)
            yield img

    return refine_estimate(est, reader, len(images), m, normals, config, method=method)


# --- errors -----------------------------------------------------------------------------------

def intensity_error(est: np.ndarray, gt: np.ndarray) -> float:
    """Scale-invariant relative intensity error of estimates [N] (grey: LCNet's) or [N, 3] (RGB:
    a matte sphere's) against ground truth [N] or [N, 3] (RGB). As the authors' evaluation for a
    grey estimate: each ground-truth channel is first divided by its first row (a grey estimate
    cannot know the lights' common colour), then mean(|s e_i - e~_i| / e~_i) over images and
    channels, s by least squares. An RGB estimate against RGB truth: the same with one s per
    channel (each channel is known up to its own scale; scoring its grey mean instead counted the
    lights' true colours as errors: 0.037 for a calibration right to 0.0006, a QA helper's finding)."""
    from psctl.metrics import intensity_relative_error

    est = np.asarray(est, np.float64)
    n = est.shape[0] if est.ndim else 1
    gt = np.asarray(gt, np.float64).reshape(n, -1)
    est = est.reshape(n, -1)
    if est.shape[1] > 1 and est.shape[1] == gt.shape[1]:
        return float(np.mean([intensity_relative_error(est[:, c], gt[:, c]) for c in range(gt.shape[1])]))
    est = est.mean(1)
    gt = gt / gt[:1]
    return intensity_relative_error(np.repeat(est[:, None], gt.shape[1], 1), gt)


def light_errors(directions: np.ndarray, intensities: np.ndarray, gt_directions: np.ndarray | None = None,
                 gt_intensities: np.ndarray | None = None) -> dict:
    """{"light_mae": mean angle (degrees) or None, "intensity_re": float or None,
    "direction_errors": [N] degrees or None}."""
    from psctl.metrics import light_direction_error

    out: dict = {"light_mae": None, "intensity_re": None, "direction_errors": None}
    if gt_directions is not None:
        err = light_direction_error(directions, gt_directions)
        out["direction_errors"] = err
        out["light_mae"] = float(err.mean())
    if gt_intensities is not None:
        out["intensity_re"] = intensity_error(intensities, gt_intensities)
    return out


# --- files and pictures -----------------------------------------------------------------------

def image_list(cap: "Capture") -> str:
    """light_images.txt's text: each image's path from the capture folder, with forward slashes
    (a list written on Windows reads on Linux, and filenames.txt's reader takes it back), or in
    full where there is no relative path (an image listed on another drive)."""
    lines = []
    for p in cap.image_paths:
        try:
            lines.append(Path(os.path.relpath(p, cap.path)).as_posix())
        except ValueError:  # Windows: another drive
            lines.append(Path(os.path.abspath(p)).as_posix())
    return "".join(f"{n}\n" for n in lines)


def write_light_files(folder: str | os.PathLike, directions: np.ndarray, intensities: np.ndarray | None,
                      names: dict[str, str] | None = None) -> dict[str, Path]:
    """light_directions.txt (N x 3) and light_intensities.txt (N x 3; one value per image is
    repeated: grey) in DiLiGenT's format (``names``: other file names for the keys
    "light_directions" and "light_intensities"); ``intensities`` None: directions only."""
    from psctl.io.atomic import write_text_atomic

    names = names or OUTPUT_FILES
    folder = Path(folder)
    d = np.asarray(directions, np.float64)
    paths = {"light_directions": folder / names["light_directions"]}
    write_text_atomic(paths["light_directions"], "".join(f"{x:.8f} {y:.8f} {z:.8f}\n" for x, y, z in d))
    if intensities is not None:
        e = np.asarray(intensities, np.float64).reshape(len(d), -1)
        if e.shape[1] == 1:
            e = np.repeat(e, 3, 1)
        paths["light_intensities"] = folder / names["light_intensities"]
        write_text_atomic(paths["light_intensities"], "".join(f"{r:.6f} {g:.6f} {b:.6f}\n" for r, g, b in e))
    return paths


def _disk(canvas: np.ndarray, cy: float, cx: float, r: float, colour, ring: float | None = None) -> None:
    """A filled disk (or, with ``ring`` = line width, a circle) of radius r at (cy, cx)."""
    H, W = canvas.shape[:2]
    pad = r + (ring or 0) + 1
    y0, y1 = max(int(cy - pad), 0), min(int(cy + pad) + 1, H)
    x0, x1 = max(int(cx - pad), 0), min(int(cx + pad) + 1, W)
    if y1 <= y0 or x1 <= x0:
        return
    yy, xx = np.ogrid[y0:y1, x0:x1]
    d = np.sqrt((yy - cy) ** 2 + (xx - cx) ** 2)
    sel = np.abs(d - r) <= ring / 2 if ring else d <= r
    canvas[y0:y1, x0:x1][sel] = colour


def _segment(canvas: np.ndarray, p0: tuple[float, float], p1: tuple[float, float], colour) -> None:
    """A one-pixel line from p0 to p1 ((row, col) each)."""
    steps = int(max(abs(p1[0] - p0[0]), abs(p1[1] - p0[1]))) + 1
    t = np.linspace(0.0, 1.0, steps + 1)
    rows = np.round(p0[0] + t * (p1[0] - p0[0])).astype(int)
    cols = np.round(p0[1] + t * (p1[1] - p0[1])).astype(int)
    ok = (rows >= 0) & (rows < canvas.shape[0]) & (cols >= 0) & (cols < canvas.shape[1])
    canvas[rows[ok], cols[ok]] = colour


def lights_plot(directions: np.ndarray, intensities: np.ndarray | None, gt_directions: np.ndarray | None = None,
                title: str | None = None, radius: int = 220, ints_range: tuple[float, float] = (0.2, 2.0)) -> np.ndarray:
    """Estimated (and true) light directions on the unit disk: [H, W, 3] in [0, 1].

    Orthographic view of the hemisphere from the camera: a direction (x, y, z) is drawn at
    (x, y), x right, y up (axes labelled +X, +Y); grey circles at 30, 60 and 90 degrees from the
    view axis. Estimates are filled dots coloured by intensity divided by the intensities' mean
    (jet over ``ints_range``, colour bar on the right, labelled), or, with ``intensities`` None (directions only: a chrome
    sphere's), all orange with no bar; ground truth, when given, is a white ring joined to its
    estimate by a grey line. A legend under the disk says which is which.
    """
    from psctl.io.report import _stamp, colour_bar, jet, text_bitmap

    s = 2  # text scale
    top, pad, bar_w, right, bottom = 20 * s, 12, 10 * s, 44 * s, 14 * s  # top: the title, then the bar's name
    side = 2 * (radius + pad)
    legend = text_bitmap("ESTIMATE" if intensities is None else "ESTIMATE, COLOUR: INTENSITY / MEAN", s)
    true = text_bitmap("TRUE", s)
    legend_w = 4 * s + 12 + legend.shape[1] + 6 * s + 16 + true.shape[1]  # with or without its TRUE: one size
    title_w = 4 * s + (text_bitmap(title, s).shape[1] if title else 0)
    # as wide as the disk and its colour bar, the legend and the title, whichever is widest
    canvas = np.full((top + side + bottom, max(side + right, legend_w + 4 * s, title_w), 3), 0.12, np.float32)
    cy, cx = top + side / 2, side / 2
    _disk(canvas, cy, cx, radius, 0.18)
    for zenith in (30.0, 60.0, 90.0):
        _disk(canvas, cy, cx, radius * np.sin(np.radians(zenith)), 0.35, ring=1.0)
    _segment(canvas, (cy, cx - radius), (cy, cx + radius), 0.3)
    _segment(canvas, (cy - radius, cx), (cy + radius, cx), 0.3)
    grey = (0.6, 0.6, 0.6)
    _stamp(canvas, text_bitmap("+Y", s), int(cy - radius) + 2 * s, int(cx) + 3 * s, grey)
    label = text_bitmap("+X", s)
    _stamp(canvas, label, int(cy) + 3 * s, int(cx + radius) - label.shape[1] - 2 * s, grey)

    def at(d: np.ndarray) -> tuple[float, float]:
        return cy - d[1] * radius, cx + d[0] * radius  # y up: row 0 is the top

    d = np.asarray(directions, np.float64).reshape(-1, 3)
    lo, hi = ints_range
    span = max(hi - lo, 1e-12)  # (a range of one value: one label, every dot in its colour)
    e = np.ones(len(d)) if intensities is None else np.asarray(intensities, np.float64).reshape(-1)
    if e.size and np.isfinite(e).all() and e.mean() > 0:
        e = e / e.mean()  # only relative intensities mean anything (LCNet's have no scale): colour them about 1
    dot = (1.0, 0.6, 0.2)  # the legend's
    colours = np.tile(dot, (len(d), 1)) if intensities is None else jet((e - lo) / span)  # clipped to the bar's ends
    if gt_directions is not None:
        g = np.asarray(gt_directions, np.float64).reshape(-1, 3)
        for k in range(len(d)):
            _segment(canvas, at(d[k]), at(g[k]), 0.6)
        for k in range(len(g)):
            _disk(canvas, *at(g[k]), 5.0, 1.0, ring=1.5)
    for k in range(len(d)):
        _disk(canvas, *at(d[k]), 3.5, colours[k])
    # each ring's angle from the view axis, where it crosses the lower-left diagonal: drawn last, in a
    # dark outline, since DiLiGenT's lights cover the 30-degree label (a QA helper found it unreadable)
    for zenith in (30.0, 60.0):
        r = radius * np.sin(np.radians(zenith)) / np.sqrt(2)
        bm, y, x = text_bitmap(f"{zenith:.0f}°", s), int(cy + r) + 2 * s, int(cx - r) - 20 * s
        for dy in (-s, 0, s):
            for dx in (-s, 0, s):
                _stamp(canvas, bm, y + dy, x + dx, (0.05, 0.05, 0.05))
        _stamp(canvas, bm, y, x, grey)
    # colour bar: high intensities on top, its name above it
    ticks = [lo, *(v for v in (0.5, 1.0, 1.5) if lo < v < hi), hi]  # 1.0, the nominal intensity, among them
    labels = {(v - lo) / span: f"{v:.1f}" for v in ticks}
    upper, lower = max(labels), min(labels)  # the bar's ends
    labels[upper] = (">" if (e > hi).any() else "") + labels[upper]
    labels[lower] = ("<" if (e < lo).any() else "") + labels[lower]
    if intensities is not None:
        colour_bar(canvas, top + pad, side + 4 * s, side - 2 * pad, bar_w, labels, s)
        _stamp(canvas, text_bitmap("INT.", s), top + pad - 9 * s, side + 2 * s)
    # legend: a dot, then a ring with its line (when there is ground truth)
    y = top + side + 3 * s
    mid = y + 3.5 * s
    _disk(canvas, mid, 4 * s + 4, 3.5, dot)
    x = 4 * s + 12
    _stamp(canvas, legend, y, x)
    x += legend.shape[1] + 6 * s
    if gt_directions is not None:
        _disk(canvas, mid, x + 6, 5.0, 1.0, ring=1.5)
        _stamp(canvas, true, y, x + 16)
    if title:
        _stamp(canvas, text_bitmap(title, s), 2 * s, 2 * s)
    return canvas


def write_lights_plot(path: str | os.PathLike, directions: np.ndarray, intensities: np.ndarray | None,
                      gt_directions: np.ndarray | None = None, light_mae: float | None = None,
                      name: str | None = None) -> None:
    """lights.png (8-bit RGB): ``name`` (the object's) and, when known, the mean direction error
    in the title."""
    from psctl.io.images import write_image

    title = "ESTIMATED LIGHTS" if light_mae is None else f"LIGHT DIRECTION MAE {light_mae:.2f}°"
    title = title if name is None else f"{name}: {title}"
    write_image(path, lights_plot(directions, intensities, gt_directions, title), "uint8")


# LCNet learnt from rigs around the view axis; with the lights to one side its estimates lean less
# than the lights do (a quarter rig's also come out nearer the axis) and the refinement does not undo
# that (a QA finding: 12 degrees, silently). On psctl's synthetic objects (benchmarks/one_sided.py,
# docs/uncalibrated.md, "One-sided rigs") the estimates' lean stayed <= 0.18 for rigs around the
# axis and was 0.35-0.84 for half, quarter and lopsided 10-light rigs
ONE_SIDED = 0.35
_SIDES = ("right", "upper right", "top", "upper left", "left", "lower left", "bottom", "lower right")


def one_sided(directions: np.ndarray) -> float:
    """How much the lights lean to one side: |mean of their image-plane parts| / mean of their
    lengths; 0 for a rig around the view axis, 1 for lights all in one direction. directions [N, 3]."""
    xy = np.asarray(directions, np.float64).reshape(-1, 3)[:, :2]
    size = float(np.linalg.norm(xy, axis=1).mean()) if len(xy) else 0.0
    return float(np.linalg.norm(xy.mean(0)) / size) if size > 1e-6 else 0.0


def one_sided_notes(directions: np.ndarray) -> list[str]:
    """A note when the estimated lights lie to one side of the view axis (``ONE_SIDED``)."""
    lean = one_sided(directions)
    if lean <= ONE_SIDED:
        return []
    mx, my = np.asarray(directions, np.float64).reshape(-1, 3)[:, :2].mean(0)
    side = _SIDES[int(np.round(np.degrees(np.arctan2(my, mx)) / 45.0)) % 8]
    return [f"lights: the estimates lie to one side of the view axis (the {side}; lean {lean:.2f}, where a rig "
            f"around the axis gives under 0.2): LCNet learnt from rigs around the axis, and on synthetic objects "
            f"lit from one side (half or a quarter of the rig) its directions came out 8.0-13.4 degrees off on "
            f"average, against 3.4-6.6 lit all around (docs/uncalibrated.md, 'One-sided rigs'); calibrate the "
            f"lights if you can (psctl calibrate)"]


# --- the object without a mask ---------------------------------------------------------------

# Why: LCNet's input has a mask channel and the light fit reads the mask's pixels; given the whole
# frame, both take the background for the object (synthetic objects before a dark background: 33.09
# degrees, 6.45 with the mask). The object of a photometric stereo capture is what the lights light:
# the lit pixels (psctl.infer.lit_pixels) with their holes filled (shadowed parts inside the
# outline) found it as well as the true mask there (6.30), and on the DiLiGenT dev split's images
# as captured (reported only) the lights came out 3.11 degrees off against 6.76 from the whole
# frame (2.89 with the true masks; docs/uncalibrated.md, "Without a mask"). Before a lit background (grey
# or textured planes) brightness cannot find it (15-60 degrees either way), the shading below can
# (since session 64); a found region that covers nearly the whole frame is read as the whole
# frame, as before, and a background that is not dark, where shading is not used, gets a note.
FOUND_MAX_FRACTION = 0.9  # a found object over this share of the frame: the whole frame instead
FOUND_MIN_PIXELS = 100  # one under this (a lit speck in a dark scene): the whole frame instead
FOUND_DARK_CONTRAST = 0.15  # the unlit part's median brightness over the lit part's mean, above which the
# background is not dark (dark backgrounds: 0.018-0.085 on syntest at albedo 0.01, 0.021-0.087 under
# DiLiGenT-like lights, 0.008-0.074 on the dev split; lit planes and textures, their border not lit:
# 0.245-0.864; benchmarks/auto_mask_lights.py's scenes)
FOUND_NORMALS_BORDER = 0.25  # the normals networks read the whole frame where the object found covers more
# of the frame's border ring (border_ring) than this: no background around it (a surface that fills the
# frame with a dark part, a review: 8.66 -> 40.6 degrees with its dark half left without normals)


# A lit background (a table, a wall) is brighter than the object's shadows, so brightness cannot
# split them; its shading can: a plane facing the camera under distant lights has one profile over
# the images at every pixel (its albedo and texture scale it), which the frame's border gives. Its
# cast shadows only darken it, and nearly to black: a background pixel's ratios to that profile are
# its level (lit) or near 0 (shadowed), where an object pixel's spread in between, as its normal
# turns it toward and away from each light. Chosen on psctl's synthetic objects before lit planes
# and textures with their cast shadows (benchmarks/auto_mask_lights.py, docs/uncalibrated.md).
FOUND_PROFILE_ELEMENTS = 16 << 20  # the profiles' grid: images x cells within this (64 MB of float32)
FOUND_PROFILE_SIDE = 256  # ... and its longer side at most this many cells (a pixel of each block)
FOUND_BORDER = 0.03  # the background's profile: the median over the frame's outer ring, this share of its side
FOUND_LEVEL = 0.9  # a cell's level: this quantile of its ratios (the lit images' ratio, on the background)
FOUND_BAND = (0.2, 0.8)  # ratios between these fractions of the level: neither lit background nor its shadow
FOUND_MID = 0.08  # a cell with more than this share of its images in the band is the object
FOUND_RELIABLE = 0.2  # the images the ratios use: the background's profile over this share of its peak
FOUND_MIN_IMAGES = 8  # fewer reliable images: no percentiles to speak of, shading not used


def profile_grid(n: int, height: int, width: int) -> int:
    """The block size (pixels per cell side) of ``n`` images' profiles over a height x width frame."""
    f = max(1, math.ceil(max(height, width) / FOUND_PROFILE_SIDE))
    while n * math.ceil(height / f) * math.ceil(width / f) > FOUND_PROFILE_ELEMENTS:
        f += 1
    return f


def block_samples(image: np.ndarray, f: int) -> np.ndarray:
    """[H, W] -> [ceil(H/f), ceil(W/f)] float32: each f x f block's centre pixel (the last blocks'
    clipped to the frame). Samples, not means: a block that a cast shadow's edge crosses would
    average to a value between lit and shadowed, which is how the object's shading differs."""
    h, w = image.shape
    rows = np.minimum(np.arange(0, h, f) + f // 2, h - 1)
    cols = np.minimum(np.arange(0, w, f) + f // 2, w - 1)
    return np.asarray(image)[np.ix_(rows, cols)].astype(np.float32)  # (sampled, then converted: not the frame)


def border_ring(height: int, width: int) -> np.ndarray:
    """[height, width] bool: the frame's outer ring, FOUND_BORDER of its shorter side (at least 1 pixel)."""
    r = max(1, round(FOUND_BORDER * min(height, width)))
    ring = np.zeros((height, width), bool)
    ring[:r], ring[-r:], ring[:, :r], ring[:, -r:] = True, True, True, True
    return ring


FOUND_REFERENCE_MAX = 8192  # the background's profile: the median of at most this many of its cells (the
# frame's border ring has under 8k on find_object's grid of at most 256 cells a side: all of them)


def unlike_background(profiles: np.ndarray, reference: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The cells whose shading differs from the background's: ``profiles`` [N, h, w] float32 (each
    cell's grey value in each image, as captured, finite), ``reference`` [h, w] bool (cells of the
    background: the frame's border, or the pixels around a mask) -> (unlike [h, w] bool, each cell
    with over FOUND_MID of its images' ratios to the background's profile between lit and shadowed;
    level [h, w] float32, its FOUND_LEVEL quantile of them: a background cell's albedo, to scale);
    None where no reference cell is lit or fewer than FOUND_MIN_IMAGES images light the background."""
    p = profiles
    ref = np.flatnonzero(reference.ravel())
    ref = ref[::-(-len(ref) // FOUND_REFERENCE_MAX)] if len(ref) > FOUND_REFERENCE_MAX else ref  # (evenly)
    edge = p.reshape(len(p), -1)[:, ref].astype(np.float64)
    total = edge.sum(0)
    edge = edge[:, total > 0] / total[total > 0]  # each cell's profile, its albedo divided out
    if edge.shape[1] == 0:
        return None
    back = np.median(edge, axis=1)  # [N]: each image's share of the background's light
    use = back > FOUND_RELIABLE * back.max()
    if int(use.sum()) < FOUND_MIN_IMAGES:
        return None
    ratio = p[use] / back[use, None, None].astype(np.float32)
    level = np.quantile(ratio, FOUND_LEVEL, axis=0)
    between = (ratio > FOUND_BAND[0] * level) & (ratio < FOUND_BAND[1] * level)
    return between.mean(0) > FOUND_MID, level.astype(np.float32)


def shading_object(profiles: np.ndarray) -> np.ndarray | None:
    """The cells whose shading differs from the background's: ``profiles`` [N, h, w] (each cell's
    grey value in each image, as captured) -> [h, w] bool, or None where the frame's border does
    not agree on one profile (no plain background to tell the object from) or fewer than
    FOUND_MIN_IMAGES images light it."""
    from scipy import ndimage

    p = np.asarray(profiles, np.float32)  # (float32: the ratios' quantiles copy them, up to 64 MB each)
    ring = border_ring(*p.shape[1:])
    found = unlike_background(p, ring)
    if found is None:
        return None
    unlike = found[0]
    if unlike[ring].mean() > 0.5:  # the border is no one background
        return None
    # holes filled first: an object's rim may be its only part unlike the background (a face turned
    # to the camera shades as the background does), one or two cells thick where the grid is coarse
    obj = ndimage.binary_opening(ndimage.binary_fill_holes(unlike), np.ones((3, 3), bool))  # no specks
    return ndimage.binary_fill_holes(object_parts(obj))


def object_parts(region: np.ndarray, share: float = 0.1) -> np.ndarray:
    """[H, W] bool -> the connected parts of ``region`` of at least ``share`` of its largest part's
    pixels: the object's parts, not crumbs (specks of noise, a lit dust grain)."""
    from scipy import ndimage

    labels, count = ndimage.label(region)
    if count < 2:
        return np.asarray(region, bool)
    sizes = ndimage.sum(region, labels, range(1, count + 1))
    return np.isin(labels, 1 + np.nonzero(sizes >= share * sizes.max())[0])


@dataclass
class FoundObject:
    """What ``find_object`` found: ``mask`` [H, W] bool, or None for the whole frame; ``info``
    {pixels, frame_fraction, contrast, used} for the report; ``notes`` for the user, each
    after a prefix that says there was no mask (the report's "mask: none (no mask.png): ", the
    array API's warning's "mask=None: ")."""
    mask: np.ndarray | None
    info: dict
    notes: list[str]

    @property
    def normals_mask(self) -> np.ndarray | None:
        """The object the normals networks read (``psctl.api``): ``mask`` where it was found by
        brightness before a dark background (``for_normals``), else None (the whole frame)."""
        return self.mask if self.mask is not None and for_normals(self.info) else None


def for_normals(info: dict) -> bool:
    """Whether the normals networks may read an object ``find_object`` found (its ``info``):
    found by brightness before a dark background (contrast at most FOUND_DARK_CONTRAST) that
    surrounds it (it covers at most FOUND_NORMALS_BORDER of the frame's border ring). Before
    a lit one, what is left out may be the object's own: a surface that fills the frame, split by
    brightness or read as a background plane by shading (a review's 48 px relief, ensemble:
    5.02 -> 33.72 degrees with its flat part left without normals), so they read the whole frame."""
    return (info["by"] == "brightness" and info["contrast"] is not None and info["contrast"] <= FOUND_DARK_CONTRAST
            and info.get("border", 0.0) <= FOUND_NORMALS_BORDER)


def find_object(brightness: np.ndarray, profiles: np.ndarray | None = None, reader: str = "lights") -> FoundObject:
    """The object of a capture without a mask, for LCNet and the light fit: ``brightness`` [H, W]
    each pixel's summed value over the images (as captured) -> the lit pixels
    (``psctl.infer.lit_pixels``, Otsu's split of log brightness) with holes filled. Where the
    unlit part is not dark (FOUND_DARK_CONTRAST: a lit background, which may be in the lit
    region) and ``profiles`` [N, h, w] are given (a pixel of each block of each image, ``profile_grid``),
    the cells whose shading differs from the background's instead (``shading_object``), when the
    frame's border agrees on one background. None (the whole frame) when the found region has
    under FOUND_MIN_PIXELS pixels or covers over FOUND_MAX_FRACTION of the frame; a note when
    the background is not dark. ``reader``: who reads the object, for the notes' words
    (``FOUND_READERS``: "lights", LCNet and the light fit; "normals", the normals networks;
    "sdps", all three)."""
    from scipy import ndimage

    from psctl.infer import lit_pixels

    who, whole, off = FOUND_READERS[reader]
    b = np.asarray(brightness, np.float64)
    b = np.where(np.isfinite(b), b, 0.0)  # NaN (a bad pixel outside the object): dark; LCNet refuses it inside
    lit = lit_pixels(b)
    region = ndimage.binary_fill_holes(lit)
    # rounded as the report gives it: for_normals reads the report's value, and the notes must agree with it
    # the unlit part's median: its mean counted the object's own dim rim where the background is black
    # (an exactly black one: a sphere's rim under oblique lights gave 0.13-0.17, median 0)
    contrast = round(float(np.median(b[~lit], overwrite_input=True) / b[lit].mean()), 4) if lit.any() and (~lit).any() and \
        b[lit].mean() > 0 else None
    not_dark = contrast is not None and contrast > FOUND_DARK_CONTRAST
    # a lit background: the unlit part is not dark, or the frame's border is lit (a background brighter
    # than a dark object: Otsu's lit part is the background, and its unlit part, the object, is dark;
    # or an object that fills the frame, whose border then agrees on no one profile: brightness stays)
    lit_background = not_dark or bool(lit[border_ring(*b.shape)].mean() > 0.5)
    by = "brightness"
    if lit_background and profiles is not None:
        p = np.asarray(profiles, np.float32)
        cells = shading_object(np.where(np.isfinite(p), p, np.float32(0)))
        if cells is not None:  # each pixel takes its cell's answer
            f = profile_grid(len(p), *b.shape)
            if cells.shape != (-(-b.shape[0] // f), -(-b.shape[1] // f)):
                raise ValueError(f"profiles {p.shape} are not profile_grid's cells of a {b.shape} frame")
            region, by = cells[np.arange(b.shape[0]) // f][:, np.arange(b.shape[1]) // f], "shading"
    frac = float(region.mean()) if region.size else 0.0
    used = int(region.sum()) >= FOUND_MIN_PIXELS and frac <= FOUND_MAX_FRACTION
    ring = border_ring(*b.shape)
    info = {"pixels": int(region.sum()), "frame_fraction": round(frac, 4),
            "contrast": None if contrast is None else round(contrast, 4), "by": by, "used": used,
            "border": round(float(region[ring].mean()), 4) if ring.any() else 0.0}
    how = ("the lit pixels, holes filled" if by == "brightness" else
           "the pixels whose shading over the images differs from the background's, holes filled")
    if used and reader != "lights" and not for_normals(info):
        # the normals networks read the whole frame (for_normals); sdps' LCNet and light fit the object
        lit = ("the background is lit (the object was told from it by shading)" if by == "shading" else
               f"the background is not dark (the unlit pixels' median brightness is {contrast:.2f} of the lit ones' mean)"
               if not_dark else f"the object found covers {info['border']:.0%} of the frame's border (no background "
                                f"around it)")
        why_not = (f"{lit}, and what is left out may be part of the object (a surface that fills the frame): "
                   f"{NO_MASK_NETWORKS_WHY}")
        if reader == "normals":
            return FoundObject(None, {**info, "used": False}, [why_not])
        who = "LCNet and the light fit"
        notes = [f"{who} read the object found by {by} ({how}: {info['pixels']} pixels, "
                 f"{frac:.0%} of the frame); a mask of the object is surer", f"the normals network: {why_not}"]
    elif used:
        notes = [f"{who} read the object found by {by} ({how}: {info['pixels']} pixels, "
                 f"{frac:.0%} of the frame); a mask of the object is surer"]
    else:
        part = "lit" if by == "brightness" else "found"
        why = ("nothing is lit" if by == "brightness" else "no part differs from the background") if \
            not region.any() else f"the {part} region covers {frac:.0%} of the frame" if \
            frac > FOUND_MAX_FRACTION else f"the {part} region has {int(region.sum())} pixels"
        notes = [f"no object found by {by} ({why}): {whole}"]
    if by == "shading" and used:
        notes.append("the background is lit: the object was told from it by shading, which assumes a background of "
                     "one plane under distant lights (synthetic objects before lit planes and textures, with their "
                     "shadows: lights 3.43 degrees off on average, 3.33 with their masks); give a mask of the object "
                     "where you can")
    elif not_dark:
        notes.append(f"the background is not dark (the unlit pixels' median brightness is {contrast:.2f} of the lit "
                     f"ones' mean): without a mask {off}; give a mask of the object")
    return FoundObject(region if used else None, info, notes)


# A mask drawn wider than the object (by hand, or grown to be safe) moves the edge LCNet reads
# away from the object's contour, which it learnt on exact masks: on psctl's synthetic objects a
# mask 3 px wider put LCNet's lights 3.9 -> 10.5 degrees off (bunny before a dark plane, 8 px: 13.9)
# and sdps' normals 5.9 -> 17.5 (bunny in white fabric), while the normals networks did not mind (the
# ensemble within 0.25 degrees on 9 objects). A mask pixel never brighter, in any image, than the
# background around the mask is background: LCNet and the light fit read the mask without such pixels.
# Where brightness cannot tell (a lit background: a table), one whose shading over the images is the
# background's, where those pixels look like the background drawn into the mask (shading_snap; since
# session 70, docs/uncalibrated.md).
SNAP_QUANTILE = 0.99  # the background's level: this quantile of the peaks outside the mask (noise, specks)
SNAP_FACTOR = 1.5  # mask pixels whose peak is at most this times that level are background
SNAP_DARK = 0.15  # ... only where that level is under this share of the kept pixels' median peak (a dark
# background: before a lit one, a dark part of the object may be no brighter than the table)
SNAP_KEEP = 0.25  # ... and where they are at least this share of the mask (else the highlights of a
# shiny object before a lit table, say: the shading snap instead); the shading snap keeps at least this
# share too (else the mask as given: a coin's flat face around a small relief shades as the table does)
SNAP_MIN_OUTSIDE = 100  # fewer pixels outside the mask: no background to measure, the mask as given
SNAP_NOTE = 0.02  # the mask as given where the snap would leave out no more than this share of it (exact
# enough: the dev split's masks lose 0-0.8%, and bear's 0.8% cost its lights 0.36 degrees), else a note
SNAP_MARGIN = 16  # before a lit background, the shading snap's background: the pixels outside the mask
# within this many of its bounding box (their median profile, as find_object's frame border gives it)
SNAP_EDGE = 0.5  # ... which leaves out pixels only where they hold at least this share of the mask's edge
SNAP_ALBEDO = 1.5  # ... and their albedo is within this factor of the surroundings' (medians)


@dataclass
class MaskEdge:
    """What ``snap_mask`` reads of the images, in one read (``capture_edge``, ``array_edge``):
    ``peak`` [H, W] float32, each pixel's brightest value over the images and channels (as
    captured; NaN and negatives 0, inf kept); ``profiles`` [N, h, w] float32, grey samples
    (``block_samples``, a pixel of each ``grid`` x ``grid`` block) of ``box``, the mask's bounding
    box grown by SNAP_MARGIN (``edge_box``), as decoded (``snap_mask`` and ``shading_snap`` read
    non-finite values and negatives as 0)."""
    peak: np.ndarray
    profiles: np.ndarray
    box: tuple[slice, slice]
    grid: int


def edge_box(mask: np.ndarray, n: int) -> tuple[tuple[slice, slice], int]:
    """The box and grid of ``n`` images' profiles for the snap: the mask's bounding box grown by
    SNAP_MARGIN (the whole frame for an empty mask), every pixel where n x its pixels fit in
    FOUND_PROFILE_ELEMENTS, else a pixel of each f x f block."""
    box = bounding_box(mask, SNAP_MARGIN) if mask.any() else (slice(0, mask.shape[0]), slice(0, mask.shape[1]))
    bh, bw = box[0].stop - box[0].start, box[1].stop - box[1].start
    f = 1
    while n * math.ceil(bh / f) * math.ceil(bw / f) > FOUND_PROFILE_ELEMENTS:
        f += 1
    return box, f


def snap_mask(edge: MaskEdge, mask: np.ndarray) -> tuple[np.ndarray, str | None]:
    """The object within a user's mask, for LCNet and the light fit: ``edge`` (what one read of
    the images gives, ``MaskEdge``), ``mask`` [H, W] bool -> (the mask snapped or as given, the note
    that says so or None).

    Before a dark background, the mask without its pixels never brighter than SNAP_FACTOR x the
    background's level (the SNAP_QUANTILE of the peaks outside the mask), holes filled, parts under
    a tenth of the largest dropped. It is dark where that level is at most SNAP_DARK of the
    brighter pixels' median peak and those are at least SNAP_KEEP of the mask and FOUND_MIN_PIXELS.
    Before a lit one, the mask without its pixels that shade over the images as the background
    around it does (``shading_snap``, with its guards), where at least SNAP_KEEP of the mask is kept.
    The mask as given where fewer than SNAP_MIN_OUTSIDE pixels lie outside it, where neither can
    tell, where under FOUND_MIN_PIXELS would be kept, and where it would leave out no more than
    SNAP_NOTE of the mask (every snap gets a note; a mask kept as given before a background that is
    not one plane gets ``unsure_note``'s, where its edge shades as that background's middle does)."""
    from scipy import ndimage

    mask = np.asarray(mask, bool)
    if not snappable(mask):
        return mask, None
    p = np.where(np.isfinite(edge.peak), np.maximum(edge.peak, 0.0), 0.0)
    outside = p[~mask]
    level = float(np.quantile(outside, SNAP_QUANTILE))
    bright = mask & (p > SNAP_FACTOR * level)
    n = int(np.count_nonzero(bright))
    if n >= max(SNAP_KEEP * np.count_nonzero(mask), FOUND_MIN_PIXELS) and \
            level <= SNAP_DARK * float(np.median(p[bright])):
        obj, by = object_parts(ndimage.binary_fill_holes(bright) & mask), "brightness"  # (a mask's own holes stay)
    else:  # a lit background (or nothing brighter than it): its shading, where it is one background
        (obj, one), by = shading_snap(edge, mask), "shading"
        if obj is None:
            return mask, None
    total, kept = int(np.count_nonzero(mask)), int(obj.sum())
    if kept < max(FOUND_MIN_PIXELS, SNAP_KEEP * total if by == "shading" else 0) or kept >= (1.0 - SNAP_NOTE) * total:
        return mask, None
    if by == "shading" and not one:  # not one background: the mask as given (what would be cut can be a face)
        return mask, unsure_note(total - kept, total)
    why = ("are never brighter than the background around it" if by == "brightness" else
           "shade over the images as the background around it does")
    return obj, (f"{total - kept} of the mask's {total} pixels ({(total - kept) / total:.0%}) {why} (or are specks "
                 f"apart from the object): LCNet and the light fit read the mask without them (LCNet learnt exact "
                 f"masks: on a synthetic bunny one 3 px wider put its lights 3.9 -> 10.5 degrees off); --no-snap "
                 f"(snap=False) reads it as given")


def unsure_note(left: int, total: int) -> str:
    """The note for a mask left as given because the cells around it do not agree on one
    background (a curved backdrop, near lights), where ``shading_snap`` would have left out
    ``left`` of its ``total`` pixels, holding at least half of its edge, every other guard passing:
    a mask likely drawn wider than the object, as LCNet reads its edge as the object's outline (an
    exact mask of a flat face turned to the camera can get it too: the note says so)."""
    return (f"{left} of the mask's {total} pixels, most of its edge among them, shade over the images as "
            f"the middle of the background around it does, but that background is not one plane under distant "
            f"lights (a curved backdrop, near lights?), where a face turned to the camera can shade so too: the "
            f"mask is read as given. If it is wider than the object, draw it tight: LCNet reads its edge as the "
            f"object's outline (on 31 such synthetic cases with masks 3-8 px wider, lights 21 degrees off on "
            f"average)")


def shading_snap(edge: MaskEdge, mask: np.ndarray) -> tuple[np.ndarray | None, bool]:
    """The object within ``mask`` [H, W] bool where its brightness cannot tell (a lit background):
    the mask's cells whose shading differs from that of the cells around it (``unlike_background``,
    the reference being the box's cells outside the mask) and its cells on the frame's edge (the
    object may run on past it), holes filled, parts under a tenth of the largest dropped -> ([H, W]
    bool within the mask or None, whether the cells around the mask agree on one background: over
    half of them like it). ``snap_mask`` takes the cut only where they agree (before a curved
    backdrop it took a coin's flat face, docs/uncalibrated.md, "Session 71"; else ``unsure_note``).
    None (the mask as given) where the images do not light the surroundings (FOUND_MIN_IMAGES), and
    where what would be left out does not look like the background drawn into the mask: it holds
    under SNAP_EDGE of the mask's edge (a wider mask's margin runs all along it; a few patches of an
    exact mask's object that shade like the background, a dragon's hollows, do not), or its albedo
    is not the surroundings' (within SNAP_ALBEDO: a coin's flat face, which shades as the table
    does, is not the table). No opening, unlike ``shading_object``: at a pixel's grain it would cut
    an object's thin parts."""
    from scipy import ndimage

    rows, cols = edge.box
    f = edge.grid
    inner = np.asarray(mask, bool)[rows, cols]
    cells = block_samples(inner, f).astype(bool)  # whether each cell's sampled pixel is in the mask
    if np.count_nonzero(~cells) * f * f < SNAP_MIN_OUTSIDE:
        return None, True
    p = np.nan_to_num(np.asarray(edge.profiles, np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    np.maximum(p, 0.0, out=p)
    found = unlike_background(p, ~cells)
    del p
    if found is None:
        return None, True
    unlike, level = found
    one = bool(unlike[~cells].mean() <= 0.5)
    h, w = mask.shape
    rim = np.zeros_like(cells)  # the cells on the frame's edge
    rim[0, :] |= rows.start == 0
    rim[-1, :] |= rows.stop == h
    rim[:, 0] |= cols.start == 0
    rim[:, -1] |= cols.stop == w
    obj = ndimage.binary_fill_holes(object_parts(ndimage.binary_fill_holes((unlike | rim) & cells)))
    out_cells = cells & ~obj
    border = cells & ~ndimage.binary_erosion(cells, border_value=1) & ~rim  # the mask's edge, in the frame
    if not out_cells.any() or not border.any() or out_cells[border].mean() < SNAP_EDGE:
        return None, one
    around, left = float(np.median(level[~cells])), float(np.median(level[out_cells]))
    if not (around > 0 and left > 0 and 1 / SNAP_ALBEDO <= left / around <= SNAP_ALBEDO):
        return None, one
    px = obj[np.arange(inner.shape[0]) // f][:, np.arange(inner.shape[1]) // f] & inner  # (a mask's own holes stay)
    out = np.zeros(mask.shape, bool)
    out[rows, cols] = px
    return out, one


def _edge(images: Iterable[np.ndarray], n: int, mask: np.ndarray,
          advance: Callable[[int], None] | None = None) -> MaskEdge:
    """``MaskEdge`` of ``n`` images [H, W, C] (or [H, W]) taken one at a time."""
    box, f = edge_box(mask, n)
    bh, bw = box[0].stop - box[0].start, box[1].stop - box[1].start
    peak = np.zeros(mask.shape, np.float32)
    profiles = np.zeros((n, -(-bh // f), -(-bw // f)), np.float32)
    for k, img in enumerate(images):
        img = img[..., None] if img.ndim == 2 else img
        np.fmax(peak, img.max(axis=-1), out=peak)  # (fmax: a NaN pixel stays 0)
        profiles[k] = block_samples(img[box].sum(-1, dtype=np.float32), f) / img.shape[-1]
        if advance is not None:
            advance(1)
    np.maximum(peak, 0.0, out=peak)
    return MaskEdge(peak, profiles, box, f)


def array_edge(images: np.ndarray, mask: np.ndarray) -> MaskEdge:
    """``capture_edge`` of in-memory images [N, H, W, 3] (or [N, H, W] grey)."""
    return _edge(images, len(images), np.asarray(mask, bool))


def snappable(mask: np.ndarray) -> bool:
    """Whether ``snap_mask`` can measure a background around ``mask`` (SNAP_MIN_OUTSIDE pixels
    outside it, and some in it): where not, the images need not be read for it."""
    mask = np.asarray(mask, bool)
    return bool(mask.any()) and np.count_nonzero(~mask) >= SNAP_MIN_OUTSIDE


def array_snap(images: np.ndarray, mask: np.ndarray | None) -> tuple[np.ndarray | None, str | None]:
    """``snap_mask`` of in-memory images with ``mask`` (None: (None, None)), as a folder's mask file
    is snapped; the edge read only where the snap can measure the background."""
    if mask is None or not snappable(mask):
        return mask, None
    return snap_mask(array_edge(images, mask), mask)


def capture_edge(capture: "Capture", mask: np.ndarray, progress: "ProgressFactory | None" = None) -> MaskEdge:
    """``MaskEdge`` of a capture's images, as captured (its light_intensities.txt not applied),
    for ``snap_mask``: one read of the images. Nothing kept in a decode memo: whole frames there
    would crowd out the crops the later passes keep."""
    from psctl.io.capture import iter_images
    from psctl.io.prefetch import prefetch

    raw = replace(capture, intensities=np.ones_like(capture.intensities))
    box = (slice(0, capture.height), slice(0, capture.width))
    advance = (progress or (lambda d, t: (lambda k: None)))(f"{capture.name}: reading the mask's edge", capture.n_images)
    with prefetch(capture.image_paths, box, (capture.width, capture.height), DEFAULT_LIGHTS["prefetch_mb"]) as pf:
        return _edge(iter_images(raw, box, decoded=pf), capture.n_images, np.asarray(mask, bool), advance)


def capture_object(capture: "Capture", mask: np.ndarray, config: dict, progress: "ProgressFactory | None" = None,
                   memo: "DecodeMemo | None" = None,
                   reader: str = "lights", snap: bool = True) -> tuple[np.ndarray, dict, FoundObject | None, str | None]:
    """What LCNet and the light fit read of a capture: (mask, LCNet's config, found, the snap's
    note). With a mask file, ``mask`` snapped to the object (``snap_mask`` of one read's
    ``capture_edge``, with its note or None), ``config`` as given and None; without one, the object ``find_object``
    finds in one read of the images (``capture_shading``: brightness and profiles; ``memo``
    keeps them), with LCNet's exposure guard reading it as a mask, or where none is found the
    whole frame (``mask``), and no note here (``found.notes``). ``reader``: as ``find_object``'s.
    ``snap`` False: a mask file as given (no read)."""
    if capture.mask_path is not None:  # (no read where snap_mask could not measure the background)
        if not snap or not snappable(mask):
            return mask, config, None, None
        snapped, note = snap_mask(capture_edge(capture, mask, progress), mask)
        return snapped, config, None, note
    found = find_object(*capture_shading(capture, progress, memo), reader=reader)
    if found.mask is None:
        return mask, config, found, None
    return found.mask, {**config, "exposure_pixels": "found"}, found, None  # its mean, as a mask's (words apart)


def capture_shading(capture: "Capture", progress: "ProgressFactory | None" = None,
                    memo: "DecodeMemo | None" = None) -> tuple[np.ndarray, np.ndarray]:
    """What ``find_object`` reads of a capture, in one read of its images: (brightness [H, W]
    float64, each pixel's sum over the images and channels as captured, its light_intensities.txt
    not applied; the profiles it tells a lit background by, [N, h, w] float32 grey, a pixel of
    each block: ``profile_grid``, ``block_samples``). ``memo`` keeps the decoded images (the whole
    frame) for the passes after, where they fit."""
    from psctl.io.capture import iter_images
    from psctl.io.prefetch import prefetch

    raw = replace(capture, intensities=np.ones_like(capture.intensities))
    box = (slice(0, capture.height), slice(0, capture.width))
    advance = (progress or (lambda d, t: (lambda k: None)))(f"{capture.name}: finding the object", capture.n_images)
    with prefetch(capture.image_paths, box, (capture.width, capture.height), DEFAULT_LIGHTS["prefetch_mb"]) as pf:
        return _shading(iter_images(raw, box, decoded=pf, memo=memo), capture.n_images, capture.height,
                        capture.width, advance)


def array_shading(images: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``capture_shading`` of in-memory images [N, H, W, 3] (or [N, H, W] grey)."""
    images = images[..., None] if images.ndim == 3 else images
    return _shading(images, *images.shape[:3])


def _shading(images: Iterable[np.ndarray], n: int, h: int, w: int,
             advance: Callable[[int], None] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The brightness and profiles of ``n`` images [h, w, C], taken one at a time (no float64 copy
    of them all)."""
    f = profile_grid(n, h, w)
    total = np.zeros((h, w), np.float64)
    profiles = np.zeros((n, -(-h // f), -(-w // f)), np.float32)
    for k, img in enumerate(images):
        grey = img.sum(-1, dtype=np.float64)
        total += grey
        profiles[k] = block_samples(grey, f) / img.shape[-1]
        if advance is not None:
            advance(1)
    return total, profiles


# --- the command ------------------------------------------------------------------------------

# LCNet's input has a mask channel, and the light fit reads the mask's pixels: without one both take
# the background for the object (a QA helper's finding: no word was said)
NO_MASK_WHY = ("LCNet and the light fit take the whole frame for the object; a mask of the object makes the lights "
               "more accurate (read whole, examples/bumpy_sphere gave 6.54 degrees, 2.45 with its mask; synthetic "
               "objects before a dark background 33.0, 6.45 with theirs)")
NO_MASK_PREFIX = "mask: none (no mask.png): "  # the array API warns "mask=None: " instead
# find_object's reader -> (who reads the object, why the whole frame is worse, what a lit background may do)
_LIGHTS_OFF = "the lights may be far off (synthetic objects before a lit plane: 15-60 degrees)"
FOUND_READERS = {
    "lights": ("LCNet and the light fit", NO_MASK_WHY, _LIGHTS_OFF),
    "normals": ("the networks", NO_MASK_NETWORKS_WHY, "the object found may take in some of the background"),
    "sdps": ("LCNet, the light fit and the normals network", NO_MASK_WHY, _LIGHTS_OFF),
}

def run_lights(path: str | os.PathLike, out: str | os.PathLike | None = None,
               weights: str | os.PathLike | None = None, device: str = "auto", decode: str = "soft",
               n_images: int | None = None, seed: int | None = None, write: bool = True,
               progress: "ProgressFactory | None" = None, views: int = DEFAULT_LIGHTS["views"],
               refine: bool = True, normals_weights: str | os.PathLike | None = None,
               falloff: str | None = None, roll: bool | None = None, encoding: str = "auto",
               light_distance: float | None = None, precision: str = "float32",
               arrays: dict | None = None, snap: bool = True) -> dict:
    """Estimate a capture folder's lights with LCNet, write them, return the report.

    ``encoding`` (auto | linear | srgb): how the images' values map to radiance
    (``psctl.io.capture.open_capture``; auto decodes files with an ICC profile through its tone curves,
    else JPEGs from sRGB, with a note).

    ``refine``: when a network that estimates normals from lights is installed (sdps' second
    stage, or ``normals_weights``), LCNet's lights are refined against its normals
    (``refine_estimate``; off with refine=False or when none is installed, which a note says);
    ``falloff`` "shifted" or "lambertian" and ``roll`` (turn the refined lights by the roll of the
    normals they give, ``roll_estimate``) override DEFAULT_REFINE's. ``light_distance`` (pixels,
    with ``refine``): the lights are points that far from the mask's centroid (without a mask
    file, the found object's) along the estimated directions, and the refinement reads the images with their falloff divided out
    (``psctl.nearlight``; LCNet reads them as captured). ``precision`` (float32, bf16, fp16): the
    refinement's normals network's arithmetic (LCNet runs in float32), as ``psctl.run_normals``'.
    ``snap`` (True): LCNet and the light fit read a mask file snapped to the object
    (``snap_mask``, noted when it leaves out over 2%, or when a mask kept as given looks drawn
    wider, ``unsure_note``); False: as given (--no-snap).

    Returns the dict printed by ``psctl lights --json``: object, n_images, light_mae and
    intensity_re (None without ground truth), outputs, plus path, device, decode, views, light_distance,
    lights_refined ({quality, weight, ...} or None), lcnet_light_mae and lcnet_intensity_re
    (LCNet's own lights), seconds, notes and provenance (``psctl.api.provenance``). Outputs (when
    ``write``, all or none): light_directions.txt, light_intensities.txt, lights.png and
    lights_report.json (this report) in ``out`` (default ``PATH/psctl``), never in the capture
    folder itself; with an ``n_images`` subset also light_images.txt.
    ``arrays`` (a dict) receives what the light files hold: "directions" [N, 3] unit vectors (x
    right, y up, z toward the camera) and "intensities" [N, 3], one row per image (with
    ``n_images``, the chosen ones).
    """
    from psctl.io.atomic import check_output_dir, output_folder, staged_outputs
    from psctl.io.capture import (check_not_capture, capture_notes, load_mask, open_capture, select_images,
                                  selection_notes)

    t0, started = time.perf_counter(), time.time()  # started: for weights files replaced during the run
    for name, value in (("path", path), ("out", out), ("weights", weights), ("normals_weights", normals_weights)):
        check_path(name, value, optional=name != "path")
    if arrays is not None and not isinstance(arrays, dict):
        raise PsctlError(None, f"arrays must be a dict (it receives the light directions and intensities), not a "
                               f"{type(arrays).__name__}")
    fit = refine_config(falloff, roll)
    write, refine = check_bool("write", write), check_bool("refine", refine)  # "no" is truthy: never a yes
    snap = check_bool("snap", snap)
    progress = check_progress(progress)
    from psctl.symmetry import check_views

    check_views(views)  # options first: their errors name the option, not the capture folder
    if decode not in ("argmax", "soft"):
        raise PsctlError(None, f"unknown --decode {decode!r}; choose argmax or soft")
    from psctl.models import check_precision, precision_autocast

    precision = check_precision(precision)
    from psctl.models.weights import installed_path
    from psctl.sdps import SDPS_SECOND

    # refined only with a normals network: asked for, but none installed, the refinement's options go unused
    refines = refine and (normals_weights is not None or any(installed_path(m) for m in SDPS_SECOND))
    second = None
    if refines:  # which network refines, decided once (a file given is checked here, before any work)
        from psctl.sdps import sdps_second_stage

        second = sdps_second_stage(normals_weights, flag="--normals-weights")[0]
    # the refinement's normals network; checked before any work (not where none will run)
    net_cfg = {"device": device, "autocast": precision_autocast(precision, device) if refines else None}
    cap = open_capture(path, encoding)
    n_all = cap.n_images
    picked = selection_notes(n_all, n_images, seed)  # never by the folder's lights: they are the answer
    cap = cap.subset(select_images(n_all, n_images, seed))
    picked += capture_notes(cap)
    subset = cap.n_images < n_all
    if subset:
        picked.append(f"images: the light files have {cap.n_images} rows, one per image listed in {SUBSET_FILE}")
    out_dir = output_folder(out, cap.path)
    if write:
        check_not_capture(out_dir, cap, (*OUTPUT_FILES.values(), FOUND_FILE, REPORT_FILE))  # its light files are inputs
        from psctl.io.atomic import check_inputs_kept

        check_inputs_kept(out_dir, [*OUTPUT_FILES.values(), SUBSET_FILE, FOUND_FILE, REPORT_FILE],
                          (("--weights", weights), ("--normals-weights", normals_weights)))
        check_output_dir(out_dir)
    mask = load_mask(cap)
    memo = None
    if refine or cap.mask_path is None:  # later passes take the images earlier ones decoded, where they fit
        from psctl.infer import DEFAULT_INFER
        from psctl.io.capture import DecodeMemo

        memo = DecodeMemo({**DEFAULT_INFER, **net_cfg}["cache_mb"] << 20)
    if light_distance is not None:
        from psctl.models.weights import installed_path
        from psctl.nearlight import check_light_distance
        from psctl.sdps import SDPS_SECOND

        check_light_distance(light_distance)  # the number now; where the lights sit, once the object is known
        if not refine:
            raise PsctlError(None, "--light-distance needs --refine: LCNet reads the images as captured, and only "
                                   "the refinement divides out the falloff")
        if normals_weights is None and not any(installed_path(m) for m in SDPS_SECOND):
            raise PsctlError(None, "--light-distance needs the light refinement, which needs a normals network "
                                   "(PS-FCN† / PS-FCN / PS-FCN+N): none is installed; name one with --normals-weights")
    from psctl.models.weights import installed_path, no_weights_error

    if weights is None and installed_path("lcnet") is None:  # before the read below, as the options' errors
        raise no_weights_error("lcnet", "--weights")
    # what LCNet and the light fit read: the mask, or the object found without one
    fit_mask, lc_cfg, found, snapped = capture_object(cap, mask, {"device": device, "decode": decode,
                                                                  "views": views}, progress, memo, snap=snap)
    picked += [] if found is None else [NO_MASK_PREFIX + n for n in found.notes]
    picked += [f"mask: {snapped}"] if snapped else []
    shown = found is not None and found.mask is not None  # read in the mask's place (and written for the user)
    near = None
    if light_distance is not None:  # the lights sit about the object's centre: the found one's without a mask
        from psctl.nearlight import near_lights, near_note

        # the centre of the user's mask (as psctl normals takes it), not of the snapped one
        near = near_lights(light_distance, fit_mask if found is not None else mask, cap.mask_path, found=shown)
        picked.append(near_note(near, "the refinement divides each image by its light's falloff (LCNet reads the "
                                      "images as captured)"))
    keep_box = None
    if refine:  # the refinement's passes take the images LCNet's decoded, where they fit
        from psctl.infer import first_read_box

        keep_box = first_read_box(cap, fit_mask, net_cfg)
    est = capture_lights(cap, fit_mask, weights, lc_cfg, progress, memo=memo, keep_box=keep_box)
    gt_ints = cap.intensities if cap.intensities_given else None
    lcnet_errors = light_errors(est.directions, est.intensities, cap.lights, gt_ints)
    if refines:
        # no normals written: the network too reads the found object only, its exposure the object's mean
        # (as a mask.png would make them; the lit pixels' rule of a capture without one split the object)
        cfg = {**net_cfg, "exposure_pixels": "found"} if shown else net_cfg
        est = _refine_capture(replace(cap, near=near), fit_mask, est, normals_weights, second, cfg, progress, fit,
                              memo)
    elif refine:
        est = replace(est, notes=[*est.notes, "lights: no normals network installed (PS-FCN† / PS-FCN / PS-FCN+N); "
                                              "LCNet's lights are not refined"])
    elif normals_weights is not None:
        est = replace(est, notes=[*est.notes, "lights: --normals-weights is unused without --refine"])
    est = replace(est, notes=[*est.notes, *one_sided_notes(est.directions)])
    from psctl.api import unused_note, unused_options

    why = "refine" if not refine else "no-network"
    unused = [unused_note(k, why) for k, _ in unused_options("sdps", refines, 1, 1, "float32", falloff, roll)]
    if not refines and precision != "float32":  # the refinement's network: LCNet alone runs in float32
        unused.append(unused_note("precision-refine", why))
    est = replace(est, notes=[*est.notes, *unused])
    if not refines:
        precision = "float32"  # LCNet's, the only network that ran
    errors = light_errors(est.directions, est.intensities, cap.lights, gt_ints)
    if arrays is not None:
        ints = np.array(est.intensities, np.float32).reshape(len(est.directions), -1)
        arrays.update(directions=np.array(est.directions, np.float32),
                      intensities=np.repeat(ints, 3, 1) if ints.shape[1] == 1 else ints)  # as the file: R G B
    report = {
        "object": cap.name,
        "path": os.path.abspath(cap.path),
        "n_images": cap.n_images,
        "light_mae": errors["light_mae"],
        "intensity_re": errors["intensity_re"],
        "outputs": {},
        "decode": est.info["decode"],
        "views": est.info["views"],
        "lights_refined": est.info.get("refine"),
        "lcnet_light_mae": lcnet_errors["light_mae"],
        "lcnet_intensity_re": lcnet_errors["intensity_re"],
        "device": est.info["device"],
        "precision": precision,
        "light_distance": None if near is None else near.distance,
        "found_object": None if found is None else found.info,
        "seconds": round(time.perf_counter() - t0, 3),
        "notes": picked + est.notes,
    }
    from psctl.api import provenance, provenance_notes, weights_used

    # LCNet's file, and the refinement's network where one ran (sdps' second stage, or --normals-weights)
    used = weights_used("sdps", normals_weights, weights, second) if refines else \
        {"lcnet": weights if weights is not None else installed_path("lcnet")}
    report["provenance"] = provenance(used, est.info["device"], started)
    report["notes"] += provenance_notes(report["provenance"])
    if subset:  # an --images subset: which images and the seed, as psctl normals reports them
        report["images_used"] = [os.path.relpath(p, cap.path) for p in cap.image_paths]
        report["seed"] = seed
    if write:
        from psctl.io.atomic import read_outputs_list, replaced_notes, write_outputs_list
        from psctl.io.report import write_json

        report["outputs"] = {k: os.path.abspath(out_dir / v) for k, v in OUTPUT_FILES.items()}
        names = [*OUTPUT_FILES.values(), *([SUBSET_FILE] if subset else []), *([FOUND_FILE] if shown else []),
                 REPORT_FILE]
        # a same-named file of the user's (a mask_found.png psctl normals wrote there is psctl's: no word)
        ours = read_outputs_list(out_dir, "lights") + [n for n in read_outputs_list(out_dir, "normals") if n == FOUND_FILE]
        report["notes"] += replaced_notes(out_dir, names, "lights", ours)
        if subset:
            report["outputs"]["light_images"] = os.path.abspath(out_dir / SUBSET_FILE)
        elif (out_dir / SUBSET_FILE).is_file():
            report["notes"].append(f"outputs: removed {SUBSET_FILE}, left by an earlier psctl lights --images run "
                                   "(these light files have a row for every image)")
        if shown:
            report["outputs"]["mask_found"] = os.path.abspath(out_dir / FOUND_FILE)
            report["notes"].append(f"{NO_MASK_PREFIX}the object found is in {FOUND_FILE}: check it; copied into the "
                                   f"capture folder as mask.png, it is read as the mask")
        # an earlier run's found object goes (one this run's list will not name); a file of the user's stays
        earlier = FOUND_FILE in read_outputs_list(out_dir, "lights") and (out_dir / FOUND_FILE).is_file()
        if earlier and not shown:
            report["notes"].append(f"outputs: removed {FOUND_FILE}, left by an earlier psctl lights run that found the "
                                   f"object (this one {'read ' + cap.mask_path.name if found is None else 'found none'})")
        # an earlier subset's list goes, and an earlier found object
        with staged_outputs(out_dir, replaces=[SUBSET_FILE, *([FOUND_FILE] if earlier else [])]) as stage:
            write_outputs_list(stage, names, "lights")
            write_light_files(stage, est.directions, est.intensities)
            if subset:
                (stage / SUBSET_FILE).write_text(image_list(cap), encoding="utf-8")
            if shown:
                from psctl.io.images import write_image

                write_image(stage / FOUND_FILE, found.mask.astype(np.float32), "uint8")
            write_lights_plot(stage / OUTPUT_FILES["lights"], est.directions, est.intensities, cap.lights,
                              errors["light_mae"], cap.name)
            report["outputs"]["report"] = os.path.abspath(out_dir / REPORT_FILE)
            report["seconds"] = round(time.perf_counter() - t0, 3)  # the file and the return agree
            write_json(stage / REPORT_FILE, report)
    return report


def _refine_capture(cap: "Capture", mask: np.ndarray, est: LightEstimate, weights: str | os.PathLike | None,
                    second: str, net_cfg: dict, progress: "ProgressFactory | None", config: dict | None = None,
                    memo: "DecodeMemo | None" = None) -> LightEstimate:
    """LCNet's lights refined against the normals that sdps' second stage gives from them (and
    turned by the roll of the normals from the refined lights when the config says so).
    ``memo``: images decoded by LCNet's pass. ``second``: the second stage's method, which
    run_lights chose once, before any work (``weights`` None: the installed network)."""
    from psctl.sdps import capture_source, second_stage

    source = capture_source(cap, mask, second, weights, net_cfg, progress, memo)
    return second_stage(source, est, True, config, normals=False)[0]


def render_lights(r: dict) -> None:
    """The human-readable summary of ``run_lights``'s report (Rich, stdout)."""
    from psctl.errors import console
    from psctl.io.summary import escape, print_notes, print_written

    con = console()
    print_notes(con, r.get("notes", []))
    line = f"[bold]{escape(r['object'])}[/]: LCNet ({r['decode']}), {r['n_images']} images, {r['seconds']:.2f} s"
    if r.get("lights_refined") and r["lights_refined"]["weight"] > 0:
        line += f", {r['lights_refined']['weight']:.0%} refined against the normals"  # as the note says
    if r["light_mae"] is not None:
        line += f"\n  light direction error [bold]{r['light_mae']:.2f}°[/] (mean)"
        if lights_changed(r.get("lights_refined")) and r.get("lcnet_light_mae") is not None:
            line += f" (LCNet alone {r['lcnet_light_mae']:.2f}°)"
    if r["intensity_re"] is not None:
        line += f", intensity relative error [bold]{r['intensity_re']:.3f}[/]"
    con.print(line, highlight=False, soft_wrap=True)
    print_written(con, r["outputs"])
